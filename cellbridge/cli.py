"""The ``cellbridge`` command.

Each layer contributes subcommands through :data:`SUBCOMMANDS`, a list of
``(name, module, help)``: the module exposes ``add_arguments(parser)`` and
``run(args) -> int``. A subcommand whose module cannot be imported (an optional
extra such as plotting is not installed) still shows in ``--help`` and explains
what is missing when run, instead of breaking the whole command.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Sequence
from typing import Any

from cellbridge._version import __version__

SUBCOMMANDS: list[tuple[str, str, str]] = [
    ("demo", "cellbridge.demo", "the whole chain: an emulated 4x4 skin, the daemon on its gateway, a press, the contact"),
    ("robot", "cellbridge.robot", "a simulated robot (MuJoCo) touches its emulated skin; contacts scored against it"),
    ("decode", "cellbridge.decode", "decode serial-line bytes (COBS frames) into readable frames"),
    ("plot", "cellbridge.plot", "draw figures of the tactile model to PNG (response: the paper's Fig. 2)"),
    ("daemon", "cellbridge.daemon.shell.cli", "run the host service: gateway serial lines in, ZeroMQ messages out"),
    ("mesh", "cellbridge.mesh_command", "generate, check, run and start emulated skins (mesh files)"),
    ("bridge", "cellbridge.emulator.realtime.process_bridge", "run one emulated bridge in real time (started by 'mesh up')"),
    ("medium", "cellbridge.emulator.realtime.process_medium", "relay cell transmissions between bridge processes (UDP on the base port)"),
    ("world", "cellbridge.emulator.realtime.process_world", "publish stimuli (contacts) to bridge processes"),
    ("press", "cellbridge.emulator.realtime.process_press", "press on a running emulated skin"),
    ("sub", "cellbridge.daemon.shell.subscribe", "print what the daemon publishes as JSON lines"),
    ("watch", "cellbridge.views.watch", "the skin in a terminal (works over SSH): forces, contacts, health"),
    ("web", "cellbridge.views.web", "the skin on a web page served on loopback, live over a WebSocket"),
    ("foxglove", "cellbridge.views.foxglove", "the skin as a Foxglove live channel (Grid, SceneUpdate, JSON)"),
    ("keys", "cellbridge.daemon.shell.keys", "CURVE key pairs for binding the daemon beyond loopback"),
    ("record", "cellbridge.recording.record_cli", "record what a daemon publishes into an MCAP file (Foxglove opens it)"),
    ("replay", "cellbridge.recording.replay", "publish an MCAP recording on ZeroMQ as the daemon published it"),
    ("info", "cellbridge.recording.info", "summarise an MCAP recording: topics, counts, duration, bridges, contacts"),
    ("ros2", "cellbridge.ros2.cli", "publish the skin on the ROS 2 graph (tactile_msgs, markers, diagnostics), no ROS install"),
    ("proxy", "cellbridge.proxy", "several daemons as one stream: libzmq's XSUB/XPUB proxy, CURVE as the daemon"),
]
#: Process entry points 'mesh up' starts: runnable (each has its --help), not listed in the top-level --help.
INTERNAL = {"bridge", "medium", "world"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cellbridge",
        description=(
            "Software for a large-area soft robot skin built on the cell-bridge system: "
            "wire protocol, tactile physics, bridge emulator and host daemon."
        ),
        epilog="Run 'cellbridge COMMAND --help' for the options of one command.",
    )
    parser.add_argument("--version", action="version", version=f"cellbridge {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name, help_text in SUBCOMMANDS:
        listed: dict[str, Any] = {} if name in INTERNAL else {"help": help_text}  # a parser given no help= is not listed
        sp = sub.add_parser(name, description=help_text, **listed)
        sp.set_defaults(_module=module_name)
        try:
            importlib.import_module(module_name).add_arguments(sp)
        except ImportError as exc:  # an optional extra is missing
            sp.set_defaults(_import_error=exc)
    return parser


#: Commands that take SIGHUP themselves (as a reload) once their handler is installed.
HANGUP_HANDLED = {"daemon"}


def main(argv: Sequence[str] | None = None) -> int:
    # SIGHUP (systemctl reload) kills a process until a handler is installed, and
    # importing the layers takes the daemon ~0.6 s: hold SIGHUP back from here on. The
    # daemon unblocks it once its handler is in place, so one sent meanwhile becomes a
    # reload; every other command gets SIGHUP's usual meaning back at once.
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGHUP})
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if args.command not in HANGUP_HANDLED:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
        if args.command is None:
            parser.print_help()
            return 2
        if getattr(args, "_import_error", None) is not None:
            print(f"cellbridge {args.command}: {args._import_error}", file=sys.stderr)
            return 1
        try:
            return int(importlib.import_module(args._module).run(args) or 0)
        except BrokenPipeError:  # the reader of the output went away (| head): its end, not an error
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (no second one at exit)
            return 0
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
