"""``cellbridge mesh up``: start an emulated skin as real processes and keep it running.

Starts the medium, the world and one ``cellbridge bridge`` process per bridge, gives
each gateway a pseudo-terminal (created here, so its device name is known before
the bridge runs), prints one line ``gateway <id> <device>`` per gateway (followed by
``socket://127.0.0.1:<port>`` with ``--tcp``), and waits. On SIGINT or SIGTERM it
stops every process it started (SIGTERM, then SIGKILL after a grace period); each
child also gets SIGTERM from the kernel if this supervisor dies, so nothing is left.
A child that dies is reported and not restarted: the others keep running (the point
of one process per bridge).
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time

from cellbridge.emulator.gateway_port import open_pty
from cellbridge.emulator.mesh import load_mesh
from cellbridge.emulator.realtime import (
    REPORTING_HELP, StopFlag, add_endpoint_arguments, die_with_parent, rate_arg, reporting_arg, reporting_text,
)

GRACE_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", help="TOML file of [[contact]] stimuli, timed from start-up")
    parser.add_argument("--seed", type=int, default=0, help="seed of chip noise, backoff and loss (default 0)")
    parser.add_argument("--rate", type=rate_arg, default=100, help="sampling rate in Hz, 1..250 (default 100)")
    parser.add_argument("--reporting", type=reporting_arg, default="periodic", metavar="MODE",
                        help=REPORTING_HELP)
    parser.add_argument("--tcp", action="store_true",
                        help="also serve each gateway's stream on a TCP port (the mesh file's 'tcp', "
                             "else a free one), usable as pyserial's socket://127.0.0.1:PORT")
    add_endpoint_arguments(parser)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "cellbridge", *args]


def run(args: argparse.Namespace) -> int:
    mesh = load_mesh(args.mesh)  # MeshError is reported by the caller
    stop = StopFlag()
    common = ["--base-port", str(args.base_port), "--host", args.host]
    children: dict[str, subprocess.Popen[bytes]] = {}
    held: list[int] = []
    lines: list[str] = []

    def spawn(name: str, cmd: list[str], pass_fds: tuple[int, ...] = ()) -> None:
        children[name] = subprocess.Popen(cmd, pass_fds=pass_fds, preexec_fn=die_with_parent,
                                          stdin=subprocess.DEVNULL)

    try:
        spawn("medium", _cmd("medium", "--mesh", args.mesh, "--seed", str(args.seed), *common))
        world = _cmd("world", "--mesh", args.mesh, *common)
        if args.scenario:
            world += ["--scenario", args.scenario]
        spawn("world", world)
        for b in mesh.bridges:
            cmd = _cmd("bridge", "--mesh", args.mesh, "--id", str(b.id), "--seed", str(args.seed),
                       "--rate", str(args.rate), "--reporting", reporting_text(args.reporting), *common)
            fds: tuple[int, ...] = ()
            if b.gateway:
                master, slave, device = open_pty()
                held.append(slave)  # keeps the line open while no host has it
                cmd += ["--pty-fd", str(master)]
                fds = (master,)
                line = f"gateway {b.id} {device}"
                if args.tcp:
                    port = b.tcp or _free_port()
                    cmd += ["--tcp", str(port)]
                    line += f" socket://127.0.0.1:{port}"
                lines.append(line)
            spawn(f"bridge {b.id}", cmd, fds)
            for fd in fds:
                os.close(fd)  # the bridge has its own copy
        for line in lines:
            print(line, flush=True)
        reported: set[str] = set()
        while not stop.stopped:
            time.sleep(0.2)
            for name, p in children.items():
                if p.poll() is not None and name not in reported:
                    reported.add(name)
                    print(f"cellbridge mesh up: {name} exited with status {p.returncode}; "
                          f"the rest keep running", file=sys.stderr, flush=True)
    finally:
        _stop_all(children)
        for fd in held:
            os.close(fd)
    return 0


def _stop_all(children: dict[str, subprocess.Popen[bytes]]) -> None:
    for p in children.values():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + GRACE_S
    for p in children.values():
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
