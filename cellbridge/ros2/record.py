"""``cellbridge record --profile ros2 OUT``: a ROS 2 bag of a running daemon.

The daemon's stream is taken as ``cellbridge ros2`` takes it (the views' ZeroMQ shell
drained into :class:`cellbridge.ros2.daemon_feed.PayloadModel`: a restarted daemon is
picked up again, the layout is asked for on the control socket), turned into ROS 2
messages (:mod:`cellbridge.ros2.convert`) and written into a bag
(:mod:`cellbridge.ros2.bag`). A message's time in the bag is when it was received here,
as ``ros2 bag record`` stamps it; its header holds the skin's own time. That time is read
on :class:`cellbridge.recording.record_cli.EpochClock` (the wall clock's at the start, the
monotonic clock's from then on), as the JSON recorder's: a wall-clock step while recording
stepped the bag's times with it, so a step back put later messages before earlier ones in
every reader's (time) order, and ``--rotate-minutes`` measured across the step.

SIGINT and SIGTERM finish the bag (exit 0); a failed write (full disk) stops it with a
message (exit 1); the counters go to stderr as one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import queue
import signal
import socket
import sys
import time
from typing import Any

from cellbridge._version import __version__
from cellbridge.ros2 import DEFAULT_FRAME, MISSING

PROFILES = ("mcap", "ros2")
#: The daemon's topics a ROS 2 bag holds (raw readings and serial bytes have no ROS 2 message here).
ROS2_TOPICS = ("contact", "element", "health", "topology")
RCVHWM = 1000  # messages ZeroMQ queues for the receiver (whose own queue is the deep one: record_cli.RCVHWM)
#: Messages decoded and converted at a time: a backlog waits as the daemon's bytes (at most
#: record_cli.BACKLOG_BYTES of them, taken off the socket by a thread of their own), not as
#: decoded payloads, which take several times their size (100 000 decoded at once were GBs).
DRAIN = 100
DEFAULT_CONTROL = "tcp://127.0.0.1:5561"


def add_profile_arguments(parser: argparse.ArgumentParser) -> None:
    """``cellbridge record``'s options for the ROS 2 profile."""
    g = parser.add_argument_group("ROS 2 bags (--profile ros2)")
    g.add_argument("--profile", choices=PROFILES, default="mcap",
                   help="mcap: JSON messages (default); ros2: a ROS 2 bag, OUT is its directory "
                        "(tactile_msgs, markers, diagnostics in CDR, metadata.yaml; see docs/ros2.md)")
    g.add_argument("--frame-id", default=DEFAULT_FRAME, metavar="FRAME",
                   help=f"the skin's frame in the bag (default: {DEFAULT_FRAME})")
    g.add_argument("--namespace", default="/cellbridge", metavar="NS", help="topic namespace (default: /cellbridge)")
    g.add_argument("--control", default=DEFAULT_CONTROL,
                   help=f"the daemon's control endpoint, asked for the layout (default: {DEFAULT_CONTROL})")


def _topics(args: argparse.Namespace) -> tuple[str, ...]:
    names = ROS2_TOPICS if args.topics == "all" else tuple(t.strip() for t in args.topics.split(",") if t.strip())
    bad = [t for t in names if t not in ROS2_TOPICS] + (["raw"] if args.raw else []) + \
        (["serial"] if args.serial else [])
    if bad:
        raise ValueError(f"a ROS 2 bag holds {', '.join(ROS2_TOPICS)}; not {bad[0]!r}")
    return tuple(dict.fromkeys([*names, "topology"]))  # the layout: the order of the readings, the picture


def run(args: argparse.Namespace) -> int:
    try:
        from cellbridge.ros2.bag import BagExists, BagWriter
        from cellbridge.ros2.convert import Converter
        from cellbridge.ros2.daemon_feed import PayloadModel
    except ImportError as exc:
        print(f"cellbridge record: --profile ros2 {MISSING} ({exc})", file=sys.stderr)
        return 1
    from cellbridge.recording.record_cli import EpochClock, Receiver, numbers_problem
    from cellbridge.ros2.cli import _others, frame_id_problem
    from cellbridge.ros2.qos import BadTopicName, topics
    from cellbridge.views.source import Source

    try:
        wanted = _topics(args)
        specs = topics(args.namespace)
        problem = numbers_problem(args) or frame_id_problem(args.frame_id)
        if problem:
            raise ValueError(problem)
        if (args.server_key is None) != (args.client_key is None):
            raise ValueError("--server-key and --client-key go together (CURVE needs both)")
    except (ValueError, BadTopicName) as exc:
        print(f"cellbridge record: {exc}", file=sys.stderr)
        return 2
    # before the bag exists: a SIGINT or SIGTERM from the moment it does finishes it (one that came
    # while the sockets were made, before, killed the recorder and left a bag no rosbag2 reader opens)
    stop: list[bool] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    meta = {"endpoint": args.endpoint, "topics": ",".join(wanted), "recorder_host": socket.gethostname(),
            "cellbridge_version": __version__, "started": f"{time.time():.6f}", "frame_id": args.frame_id}
    try:
        bag = BagWriter(args.out, specs, chunk_size=int(args.chunk_size * 1e6), compression=args.compression,
                        fsync=not args.no_fsync, rotate_bytes=int(args.rotate_size * 1e6),
                        rotate_seconds=args.rotate_minutes * 60, metadata=meta)
    except (BagExists, OSError) as exc:
        print(f"cellbridge record: {exc}", file=sys.stderr)
        return 2
    try:
        # health always: a restarted daemon is known by its health numbering starting again (the
        # layout asked anew, the old process's contacts ended); in the bag only when asked for
        heard = wanted if "health" in wanted else (*wanted, "health")
        source = Source(args.endpoint, args.control, args.server_key, args.client_key, topics=heard, rcvhwm=RCVHWM)
    except (ValueError, OSError) as exc:
        bag.finish()
        print(f"cellbridge record: {exc}", file=sys.stderr)
        return 2
    clock = EpochClock()
    converter = Converter(args.frame_id)
    model = PayloadModel(converter)
    received, error = 0, ""
    stats: dict[str, Any] = {}
    end = None if args.duration is None else time.monotonic() + args.duration  # (record_cli checked both limits)
    flushed = time.monotonic()
    # the daemon's socket is the receiver's alone from here: it holds at most BACKLOG_BYTES of
    # messages not yet converted, and takes (and counts) the rest off the socket, so that neither
    # its queue nor ZeroMQ's grows by the size of large messages the conversion is behind on
    receiver = Receiver(source.sub, clock)
    receiver.start()

    def convert(timeout: float) -> bool:
        """Convert and write the next batch of what the receiver took (False: none came)."""
        nonlocal received, flushed, error
        batch: list[list[bytes]] = []
        room = DRAIN if args.count is None else min(DRAIN, args.count - received)
        with contextlib.suppress(queue.Empty):
            batch.append(receiver.get(timeout=timeout)[0])
            while len(batch) < room:
                batch.append(receiver.get(timeout=0)[0])
        source.feed_received(model, batch)
        try:
            for topic, payload, arrived in model.take():
                if topic not in wanted:  # (health heard for the restarts alone)
                    continue
                received += 1
                now_ns = int(clock() * 1e9)
                # the pictures' rate on the arrival (monotonic), as 'cellbridge ros2' counts it: on the
                # daemon's t_host a step back of its clock left the bag without a picture for as long
                for key, message in converter.feed(topic, payload, arrived):
                    bag.add(key, message, now_ns)
            if args.chunk_seconds and time.monotonic() - flushed >= args.chunk_seconds:
                flushed = time.monotonic()
                bag.flush()
        except OSError as exc:
            error = f"{args.out}: {exc.strerror or exc}; recording stopped (the bag keeps its whole chunks)"
            bag.abandon()
        return bool(batch)

    try:
        while not stop and not error and (args.count is None or received < args.count):
            if end is not None and time.monotonic() >= end:
                break
            if receiver.error is not None:
                error = f"{args.endpoint}: {receiver.error}"
                break
            convert(0.1)
        receiver.stop.set()
        receiver.join()
        if stop:  # what was received before the signal goes into the bag too
            while not error and (args.count is None or received < args.count) and convert(0):
                pass
    finally:
        receiver.stop.set()
        receiver.join()
        source.close()
        if not error:
            try:
                bag.finish()
            except OSError as exc:
                error = f"{args.out}: {exc.strerror or exc}"
        stats = {"recorded": {specs[k].name: n for k, n in bag.counts.items()}, "messages": bag.messages,
                 "received": received, "lost": model.lost, "malformed": model.malformed + converter.malformed,
                 "newer_schema": converter.newer_schema, "unknown_topics": model.unknown_topics,
                 "daemon_restarts": model.daemon_restarts, "source": model.source,
                 "other_sources": _others(model), "files": [str(f.path) for f in bag.files], "error": error,
                 "behind": receiver.discarded}
        print(json.dumps(stats), file=sys.stderr)
    if error:
        print(f"cellbridge record: {error}", file=sys.stderr)
        return 1
    return 0
