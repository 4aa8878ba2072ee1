"""``cellbridge daemon``: the host service that turns gateway serial lines into ZeroMQ messages."""

from __future__ import annotations

import argparse
import sys

from cellbridge.daemon.core.config import Config, ConfigError, default_toml, load_config
from cellbridge.daemon.core.wire import OPS
from cellbridge.daemon.shell.capture import capture_problem

DESCRIPTION = """\
Read the skin's gateway serial lines and publish contacts, per-element force and area,
raw readings, health and topology on ZeroMQ; accept control requests (status, tare,
set {params}, topology, ping).

Start by printing the defaults into a file and adding your gateway(s):

  cellbridge daemon --print-config > cellbridge.toml
  $EDITOR cellbridge.toml          # a [[link]] per gateway: url = "/dev/ttyUSB0"
  cellbridge daemon --config cellbridge.toml --check
  cellbridge daemon --config cellbridge.toml

Link URLs are pyserial URLs (/dev/ttyUSB0, a pty path, socket://HOST:PORT) or
replay:FILE to play back a capture recorded with the link's `capture = "FILE"` key,
or an MCAP recording made with `cellbridge record --serial` (docs/recording.md).
Subscribers connect to tcp://127.0.0.1:5560 (topics contact, element, raw, health,
topology, serial; msgpack payloads); control is a msgpack request/reply on
tcp://127.0.0.1:5561.
docs/zmq-api.md describes every message. SIGTERM drains and exits 0; SIGHUP reloads
the settings marked (reload) in --print-config (one sent during start-up is taken once
the daemon is up). Clients are bounded by [peers]: connections per socket and per
address, handshake time; the descriptor limit must hold them (docs/zmq-api.md, Limits).
On real hardware name a gateway by /dev/serial/by-id/..., which survives re-plugging.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = DESCRIPTION.format(params="/".join(OPS))
    parser.add_argument("--config", "-c", metavar="FILE", help="TOML configuration (see --print-config)")
    parser.add_argument("--print-config", action="store_true",
                        help="print every setting with its default and meaning, then exit")
    parser.add_argument("--check", action="store_true",
                        help="validate the configuration and the layout file, then exit (0 when fine)")


def _load(args: argparse.Namespace) -> Config:
    config = load_config(args.config)
    if not config.links:
        raise ConfigError(config.source, ["no [[link]] configured: add one per gateway (url = ...)"])
    from cellbridge.daemon.shell.service import read_layout

    read_layout(config)  # a bad layout file is a config error too
    from cellbridge.daemon.ops.ops import curve_keys
    from cellbridge.daemon.ops.security import check_bind

    curve = curve_keys(config)  # and so are missing or unsafe CURVE key files
    for endpoint in (config.pub.endpoint, config.control.endpoint):  # and a bind beyond loopback without them
        check_bind(endpoint, curve)
    from cellbridge.daemon.ops.peers import reserve_descriptors

    reserve_descriptors(config)  # and a descriptor limit that cannot hold the peers it admits
    return config


def run(args: argparse.Namespace) -> int:
    if args.print_config:
        sys.stdout.write(default_toml())
        return 0
    if not args.config:
        print("cellbridge daemon: --config FILE is required (start from --print-config)", file=sys.stderr)
        return 2
    try:
        config = _load(args)
    except (ConfigError, ValueError) as exc:
        print(f"cellbridge daemon: {exc}", file=sys.stderr)
        return 2
    # A capture that cannot be written costs the capture, not the daemon (the link runs,
    # health names capture_error); --check says so before it happens.
    captures = [f"link[{i}].capture = {ln.capture!r}: {why}" for i, ln in enumerate(config.links)
                if ln.capture and (why := capture_problem(ln.capture))]
    if args.check:
        if captures:
            print(f"cellbridge daemon: {ConfigError(config.source, captures)}", file=sys.stderr)
            return 2
        print(f"{config.source}: ok ({len(config.links)} link(s))")
        return 0
    for problem in captures:
        print(f"cellbridge daemon: warning: {problem}; the link runs without its capture", file=sys.stderr)
    from cellbridge.daemon.shell.service import run_service

    return run_service(args.config, config)
