"""``cellbridge ros2``: the skin on the ROS 2 graph, live, without a ROS installation.

A subscriber of the daemon like any view (:mod:`cellbridge.views.source`: it picks a
restarted daemon up again) that publishes what it gets as ROS 2 messages
(:mod:`cellbridge.ros2.convert`) through Cyclone DDS (:mod:`cellbridge.ros2.graph`).
SIGINT, SIGTERM and SIGHUP stop it; it then prints its counters as one JSON line on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time

from cellbridge.ros2 import DEFAULT_FRAME, MISSING
from cellbridge.ros2.qos import BadTopicName, topics
from cellbridge.tactile.skin_geometry import MAX_NAME, frame_name
from cellbridge.views.model import SkinView
from cellbridge.views.source import add_source_arguments, open_source


def _default_domain() -> int:
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", "0"))
    except ValueError:
        return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Publish a running daemon's skin on the ROS 2 graph (DDS, through Cyclone DDS: no ROS\n"
        "installation needed), in the tactile community's messages (tactile_msgs, whose .msg\n"
        "files ship in cellbridge/ros2/interfaces/) and standard ones:\n"
        "  /cellbridge/tactile_state  tactile_msgs/msg/TactileState      every element's force, area, dC1, dC2\n"
        "  /cellbridge/contacts       tactile_msgs/msg/TactileContacts   position, normal, wrench per contact\n"
        "  /cellbridge/markers        visualization_msgs/msg/MarkerArray the skin's picture for rviz and Foxglove\n"
        "  /diagnostics               diagnostic_msgs/msg/DiagnosticArray the daemon's, links' and bridges' health\n"
        "Readings are best effort (ROS 2's sensor-data QoS); contacts, markers and diagnostics\n"
        "reliable. A flat skin is in one frame (--frame-id); a contact on a robot's skin is in\n"
        "the frame of the link it is on. See docs/ros2.md.\n\n"
        "DDS stays on loopback unless told otherwise (--interface): ROS 2 nodes on this machine\n"
        "see the topics; for other machines name the network interface.\n\n"
        "examples:\n"
        "  cellbridge ros2                              # domain $ROS_DOMAIN_ID (or 0), loopback\n"
        "  cellbridge ros2 --domain 7 --frame-id left_forearm\n"
        "  cellbridge ros2 --interface eth0             # ROS 2 nodes on other machines too\n"
        "  ros2 topic echo /cellbridge/contacts        # in a ROS 2 shell, with tactile_msgs built"
    )
    add_source_arguments(parser)
    g = parser.add_argument_group("ROS 2")
    g.add_argument("--domain", type=int, default=_default_domain(), metavar="N",
                   help="ROS 2 domain id, 0..232 (default: $ROS_DOMAIN_ID, else 0)")
    g.add_argument("--interface", default="lo", metavar="NAME",
                   help="network interface DDS uses (default: lo, this machine only; e.g. eth0 to reach others)")
    g.add_argument("--dds-config", metavar="XML|FILE",
                   help="a whole Cyclone DDS configuration (XML text, or file://PATH) instead of --interface's")
    g.add_argument("--namespace", default="/cellbridge", metavar="NS",
                   help="topic namespace (default: /cellbridge)")
    g.add_argument("--diagnostics-topic", default="/diagnostics", metavar="TOPIC",
                   help="where the health goes (default: /diagnostics, where ROS 2's diagnostic tools look)")
    g.add_argument("--frame-id", default=DEFAULT_FRAME, metavar="FRAME",
                   help=f"the skin's frame (default: {DEFAULT_FRAME})")
    g.add_argument("--marker-rate", type=float, default=10.0, metavar="HZ",
                   help="most skin pictures (markers) a second, besides one whenever the contacts come or go "
                        "(default: 10)")
    g.add_argument("--diagnostics-rate", type=float, default=1.0, metavar="HZ",
                   help="most diagnostics a second, besides one whenever the daemon's level (OK, WARN, ERROR) "
                        "changes; the daemon's other health messages are left out, and counted (default: 1, "
                        "what ROS 2's diagnostic tools expect; the daemon sends one every [health] interval, 1 s by "
                        "default)")


def _problem(args: argparse.Namespace) -> str | None:
    try:
        topics(args.namespace, args.diagnostics_topic)
    except BadTopicName as exc:
        return str(exc)
    if not 0 <= args.domain <= 232:
        return f"--domain must be within 0..232 (ROS_DOMAIN_ID), got {args.domain}"
    if not 0.1 <= args.marker_rate <= 1000:
        return f"--marker-rate must be within 0.1..1000, got {args.marker_rate}"
    if not 0.1 <= args.diagnostics_rate <= 1000:
        return f"--diagnostics-rate must be within 0.1..1000, got {args.diagnostics_rate}"
    return frame_id_problem(args.frame_id)


def frame_id_problem(frame_id: str) -> str | None:
    """Why ``--frame-id`` names no frame (empty, too long, a control character: as a link's
    name is checked, since it is every flat-skin message's ``frame_id``), or None."""
    if frame_name(frame_id) is None:
        return (f"--frame-id must be a name of 1 to {MAX_NAME} characters, none a control character, "
                f"got {frame_id[:80]!r}")
    return None


def _others(model: SkinView) -> dict[str, int]:
    """Messages of daemons other than the one published (several behind a proxy), by source."""
    others = dict(model.other_sources)
    if model.other_sources_more:
        others["(more)"] = model.other_sources_more
    return others


def run(args: argparse.Namespace) -> int:
    try:
        from cellbridge.ros2.convert import Converter
        from cellbridge.ros2.daemon_feed import PayloadModel
        from cellbridge.ros2.graph import BadInterface, Graph, dds_config
        from cellbridge.ros2.relay import Relay
    except ImportError as exc:
        print(f"cellbridge ros2: {MISSING} ({exc})", file=sys.stderr)
        return 1
    stop = threading.Event()  # (before the sockets and DDS are made: a signal meanwhile still prints the counters)
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    source = open_source("ros2", args, _problem(args))
    if source is None:
        return 2
    specs = topics(args.namespace, args.diagnostics_topic)
    converter = Converter(args.frame_id, marker_period=1.0 / args.marker_rate, force_scale=args.force_scale,
                          diagnostics_period=1.0 / args.diagnostics_rate)
    model = PayloadModel(converter, force_scale=args.force_scale, source=args.source)
    graph: Graph | None = None
    try:
        try:
            config = args.dds_config if args.dds_config else dds_config(args.interface)
            graph = Graph(args.domain, specs, config)
        except (BadInterface, ValueError) as exc:
            print(f"cellbridge ros2: {exc}", file=sys.stderr)
            return 2
        except Exception as exc:
            print(f"cellbridge ros2: cannot join ROS 2 domain {args.domain}: {exc}", file=sys.stderr)
            return 1
        print(f"cellbridge ros2: domain {args.domain} ({args.interface if not args.dds_config else 'own config'}): "
              + ", ".join(s.name for s in specs.values()), flush=True)
        # contacts first, also those that arrive while a large message is being worked on
        relay = Relay(source, model, converter, graph.publish, stop.is_set)
        while not stop.is_set():
            relay.step(100)
    finally:
        if graph is not None:
            graph.close()
        source.close()
        print(json.dumps({"published": graph.published if graph is not None else {},
                          "dropped": graph.dropped if graph is not None else {},
                          "malformed": model.malformed + converter.malformed, "newer_schema": converter.newer_schema,
                          "unknown_topics": model.unknown_topics,
                          "lost": model.lost,
                          "health_not_published": converter.diagnostics_skipped,
                          "daemon_restarts": model.daemon_restarts, "source": model.source,
                          "other_sources": _others(model), "t": round(time.time(), 3)}), file=sys.stderr)
    return 0

