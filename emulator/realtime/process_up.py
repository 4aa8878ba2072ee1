"""``cellbridge mesh up``: start an emulated skin as real processes and keep it running.

Starts the medium, the world and one ``cellbridge bridge`` process per bridge, gives
each gateway a pseudo-terminal (created here, so its device name is known before
the bridge runs), prints one line ``gateway <id> <device>`` per gateway (followed by
``socket://127.0.0.1:<port>`` with ``--tcp``), and waits. On SIGINT or SIGTERM it
stops every process it started (SIGTERM, then SIGKILL after a grace period); each
child also gets SIGTERM from the kernel if this supervisor dies, so nothing is left.
A child that dies is reported and not restarted: the others keep running (the point
of one process per bridge).

Bridge processes are forked from this supervisor, which has imported what a bridge
needs once, rather than started as new interpreters: a new interpreter spends ~0.25 s
of CPU importing, and 64 of them at once held both cores of a small machine for
seconds, while the first bridges were already routing (late acknowledgements, then
route churn that outlived the start). A forked bridge costs ~25 ms. Each one's
process title is the ``cellbridge bridge ...`` command it runs, as ``ps`` shows.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import signal
import socket
import subprocess
import sys
import time
import traceback

import setproctitle
from cellbridge.emulator.mesh.mesh import Bridge, Mesh, load_mesh
from cellbridge.emulator.realtime import process_bridge
from cellbridge.emulator.realtime.gateway_port import open_pty
from cellbridge.emulator.realtime.mesh_cli import warn_if_not_fitting
from cellbridge.emulator.realtime.pty_link import link_folder_problem, link_gateway
from cellbridge.emulator.realtime.realtime import (
    REPORTING_HELP,
    StopFlag,
    add_endpoint_arguments,
    die_with_parent,
    rate_arg,
    reporting_arg,
    reporting_text,
    seconds_arg,
)
from cellbridge.emulator.world.world import check_on_skin, load_scenario

GRACE_S = 5.0
#: Between two bridges' starts. A whole 8x8 skin forked at once (64 bridges in ~1.5 s)
#: held a 2-core machine busy while routes formed: acknowledgements came late, links
#: looked lossy, parents flipped (7 500 parent changes in 25 s, 1 of 9 frames acknowledged)
#: and the churn outlived the start. 0.1 s apart: 134 parent changes, no failed frame.
START_INTERVAL_S = 0.1
_MAXFD = os.sysconf("SC_OPEN_MAX")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", help="TOML file of [[contact]] stimuli, timed from start-up")
    parser.add_argument("--seed", type=int, default=0, help="seed of chip noise, backoff and loss (default 0)")
    parser.add_argument("--rate", type=rate_arg, default=100, help="sampling rate in Hz, 1..250 (default 100)")
    parser.add_argument("--reporting", type=reporting_arg, default="periodic", metavar="MODE",
                        help=REPORTING_HELP)
    parser.add_argument("--readout", choices=("on", "off"), default="on",
                        help="on (default): samples on mesh time are read out frame by frame in READOUT "
                             "records (docs/time.md); off: every sample in DATA frames, as a skin before "
                             "the readout sent them")
    parser.add_argument("--tcp", action="store_true",
                        help="also serve each gateway's stream on a TCP port (the mesh file's 'tcp', "
                             "else a free one), usable as pyserial's socket://127.0.0.1:PORT")
    parser.add_argument("--start-interval", type=seconds_arg, default=START_INTERVAL_S, metavar="SECONDS",
                        help=f"pause between two bridges' starts, gateways first, then outwards "
                             f"(default {START_INTERVAL_S}: on a small machine a whole skin booting at "
                             f"once delays acknowledgements until routes churn)")
    parser.add_argument("--pty-link", metavar="DIR",
                        help="also keep a symlink DIR/gateway-<id> to each gateway's pty (its /dev/pts number "
                             "changes on every start; configure the daemon with the link); DIR is made "
                             "if missing")
    add_endpoint_arguments(parser)


def start_order(mesh: Mesh) -> list[Bridge]:
    """Gateways first, then bridges by hops from them (breadth first), unreachable ones
    last: each bridge then boots beside neighbours that already have a route, as a skin
    that grows, and its first beacons find a settled tree."""
    hops = mesh.hops()  # breadth first from the gateways, in that order
    order = [*hops, *(b for b in mesh.ids if b not in hops)]
    return [mesh.bridge(b) for b in order]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "cellbridge", *args]


class ForkedBridge:
    """A bridge process forked from this one, with the part of ``subprocess.Popen``'s
    interface the supervisor uses."""

    def __init__(self, argv: list[str], keep_fd: int | None) -> None:
        self.args = argv
        self.returncode: int | None = None
        sys.stdout.flush()
        sys.stderr.flush()
        supervisor = os.getpid()
        pid = os.fork()
        if pid == 0:  # the bridge: never returns into the supervisor's code
            code = 1
            try:  # not even by an exception (a last word to a stderr nobody reads: EPIPE)
                code = _bridge_main(argv, keep_fd, supervisor)
            finally:
                os._exit(code)
        self.pid = pid

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        end = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if end is not None and time.monotonic() >= end:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            time.sleep(0.02)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _bridge_main(argv: list[str], keep_fd: int | None, supervisor: int) -> int:
    """The forked child: drop what belongs to the supervisor, then run ``cellbridge bridge``."""
    try:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # until the bridge installs its own
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        die_with_parent()
        if os.getppid() != supervisor:  # it died before the death signal was armed
            return 1
        # Nothing of the supervisor's but stdout, stderr and this bridge's own pty: not the
        # other gateways' held lines, nor what mesh up's launcher left open
        # (a bridge holding a pipe its launcher waits on for EOF), as subprocess's close_fds.
        if keep_fd is None:
            os.closerange(3, _MAXFD)
        else:
            os.closerange(3, keep_fd)
            os.closerange(keep_fd + 1, _MAXFD)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        setproctitle.setproctitle(" ".join(_cmd(*argv)))
        parser = argparse.ArgumentParser(prog="cellbridge bridge")
        process_bridge.add_arguments(parser)
        code = process_bridge.run(parser.parse_args(argv[1:]))
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    return code


def run(args: argparse.Namespace) -> int:
    mesh = load_mesh(args.mesh)  # MeshError is reported by the caller
    if args.scenario:  # read here too (ScenarioError, as MeshError): a bad one is said before anything starts
        for i, contact in enumerate(load_scenario(args.scenario)):
            check_on_skin(mesh, contact, f"{args.scenario}: contact[{i}]")
    if args.readout == "on":  # (the shells send records unacknowledged: process_bridge)
        warn_if_not_fitting(mesh, args.rate, acked=False)
    stop = StopFlag()
    common = ["--base-port", str(args.base_port), "--host", args.host]
    children: dict[str, subprocess.Popen[bytes] | ForkedBridge] = {}
    held: list[int] = []
    lines: list[str] = []

    def spawn(name: str, cmd: list[str], pass_fds: tuple[int, ...] = ()) -> None:
        children[name] = subprocess.Popen(cmd, pass_fds=pass_fds, preexec_fn=die_with_parent,
                                          stdin=subprocess.DEVNULL)

    if args.pty_link:  # (made now: a folder that cannot be is said before anything starts)
        problem = link_folder_problem(args.pty_link)
        if problem:
            _report(f"cellbridge mesh up: {problem}. Nothing started.")
            return 2
    # Claimed first, held for this process's life: two mesh ups started at once both found
    # the ports free, and each took the other's bound port for its own failure.
    claims = claim_base_port(args.base_port)
    if not claims:
        _report(f"cellbridge mesh up: base port {args.base_port}: another mesh up on this host holds it "
                f"(UDP {args.base_port}, TCP {args.base_port + 1} and {args.base_port + 2}); choose another "
                f"--base-port. Nothing started.")
        return 1
    busy = ports_in_use(args.host, args.base_port)
    if busy:
        for c in claims:
            c.close()
        _report(f"cellbridge mesh up: base port {args.base_port}: {busy} already in use (another mesh up "
                f"on it?); choose another --base-port. Nothing started.")
        return 1
    try:
        readies = []
        for name, cmd in (("medium", _cmd("medium", "--mesh", args.mesh, "--seed", str(args.seed), *common)),
                          ("world", _cmd("world", "--mesh", args.mesh, *common,
                                         *(["--scenario", args.scenario] if args.scenario else [])))):
            r, w = os.pipe()
            try:
                spawn(name, [*cmd, "--ready-fd", str(w)], pass_fds=(w,))
            finally:
                os.close(w)
            readies.append((name, r))
        failed = [name for name, r in readies if not _wait_ready(r, children[name], stop)]
        if stop.stopped:
            return 0
        if failed:
            what = {"medium": f"UDP {args.host}:{args.base_port}",
                    "world": f"TCP {args.host}:{args.base_port + 1} and :{args.base_port + 2}"}
            _report(f"cellbridge mesh up: the {' and the '.join(failed)} did not start on base port "
                    f"{args.base_port} ({'; '.join(what[n] for n in failed)}); no bridge started")
            return 1
        started, n_gateways = 0, len(mesh.gateways)
        for b in start_order(mesh):
            argv = ["bridge", "--mesh", args.mesh, "--id", str(b.id), "--seed", str(args.seed),
                    "--rate", str(args.rate), "--reporting", reporting_text(args.reporting),
                    "--readout", args.readout, *common]
            master = None
            if b.gateway:
                master, slave, device = open_pty()
                held.append(slave)  # keeps the line open while no host has it
                argv += ["--pty-fd", str(master)]
                line = f"gateway {b.id} {device}"
                if args.tcp:
                    port = b.tcp or _free_port()
                    argv += ["--tcp", str(port)]
                    line += f" socket://127.0.0.1:{port}"
                if args.pty_link:
                    line += f" {link_gateway(args.pty_link, b.id, device)}"
                lines.append(line)
            if started:
                _pause(args.start_interval, stop)
            if stop.stopped:
                break
            children[f"bridge {b.id}"] = ForkedBridge(argv, master)
            started += 1
            if master is not None:
                os.close(master)  # the bridge has its own copy
            if started == len(lines) == n_gateways:  # gateways start first: their lines at once
                for line in lines:
                    print(line, flush=True)
        reported: set[str] = set()
        while not stop.stopped:
            _pause(0.2, stop)
            for name, p in children.items():
                # Ctrl-C signals the whole process group: the children exit as this
                # supervisor stops, and their exits are that stop, not failures to report
                if stop.stopped:
                    break
                if p.poll() is not None and name not in reported:
                    reported.add(name)
                    _report(f"cellbridge mesh up: {name} exited with status {p.returncode}; "
                            f"the rest keep running")
    finally:
        _stop_all(children)
        for fd in held:
            os.close(fd)
        for c in claims:
            c.close()
    return 0


def _pause(seconds: float, stop: StopFlag) -> None:
    """Wait ``seconds`` or until SIGINT/SIGTERM, whichever comes first. Not one
    ``time.sleep``: it resumes after a signal's handler (PEP 475), so a SIGTERM during a
    long --start-interval would wait for its end, and beyond time_t it raises."""
    end = time.monotonic() + seconds
    while not stop.stopped and (left := end - time.monotonic()) > 0:
        time.sleep(min(left, 0.05))


def _report(line: str) -> None:
    """A line on stderr; when nobody reads it any more (``mesh up 2>&1 | grep ...`` ended),
    the line is lost, not the skin: the rest keep running, as the line says."""
    try:
        print(line, file=sys.stderr, flush=True)
    except OSError:
        pass


def claim_base_port(base: int) -> list[socket.socket]:
    """Claim the base port's three ports (UDP base, TCP base+1, base+2) for this process
    before anything binds them: an abstract Unix socket per port, which a second mesh up
    cannot bind and the kernel releases when this process dies, however it dies. Empty
    when another process holds one of them. Checking that the ports are free, then starting
    the medium and world, left a window (an interpreter's start, seconds on a loaded
    machine) in which a second mesh up found them free too. Keyed by the port alone, not
    the ``--host``: 0.0.0.0 and 127.0.0.1 share ports."""
    claims: list[socket.socket] = []
    for name in (f"udp/{base}", f"tcp/{base + 1}", f"tcp/{base + 2}"):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.bind(f"\0cellbridge-mesh-port/{name}")
        except OSError:
            s.close()
            for c in claims:
                c.close()
            return []
        claims.append(s)
    return claims


def ports_in_use(host: str, base: int) -> str:
    """Which of the base port's three (UDP base, TCP base+1, base+2) this host has bound
    already, as text ('' when all are free). A quick check for a clear message; the
    readiness of the medium and world is what proves they bound them."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    busy = []
    for kind, port, what in ((socket.SOCK_DGRAM, base, "UDP"), (socket.SOCK_STREAM, base + 1, "TCP"),
                             (socket.SOCK_STREAM, base + 2, "TCP")):
        with socket.socket(family, kind) as s:
            if kind == socket.SOCK_STREAM:  # as ZeroMQ binds: a closed mesh's TIME_WAIT is no user
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    busy.append(f"{what} {host}:{port}")
    return ", ".join(busy)


def _wait_ready(fd: int, proc: subprocess.Popen[bytes] | ForkedBridge, stop: StopFlag, seconds: float = 60.0) -> bool:
    """Whether the process said it bound its ports (a line on its ready pipe) before it
    exited, closed the pipe, or ``seconds`` passed (a loaded machine may take seconds to
    start an interpreter). Closes ``fd``."""
    end = time.monotonic() + seconds
    got = b""
    try:
        while not stop.stopped and (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select([fd], [], [], min(left, 0.2))
            if ready:
                chunk = os.read(fd, 64)
                if not chunk:
                    break
                got += chunk
                if b"\n" in got:
                    return got.startswith(b"ready")
            elif proc.poll() is not None:
                break
        return False
    finally:
        os.close(fd)


def _stop_all(children: dict[str, subprocess.Popen[bytes] | ForkedBridge]) -> None:
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
