"""What the real-time process shells share: the clock, the endpoints (UDP medium, ZeroMQ world), shutdown.

Every process on one host reads the same monotonic clock, so a tick (a 50 MHz cycle
of host time) means the same instant in the medium and in every bridge: carrier
reports and deliveries need no clock exchange. Endpoints are derived from one base
port so that ``mesh up``, ``bridge``, ``medium``, ``world`` and ``press`` agree without
a registry: medium = UDP base, world stimuli = TCP base + 1, world control = TCP base + 2.
"""

from __future__ import annotations

import argparse
import ctypes
import math
import os
import signal
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cellbridge.emulator.firmware.reporting import ReportingMode

CLOCK_HZ = 50_000_000
DEFAULT_BASE_PORT = 5570
LOOPBACK = "127.0.0.1"


def now_tick() -> int:
    return int(time.monotonic() * CLOCK_HZ)


def tick_seconds(tick: int) -> float:
    return tick / CLOCK_HZ


@dataclass(frozen=True)
class Endpoints:
    host: str = LOOPBACK
    base_port: int = DEFAULT_BASE_PORT

    @property
    def medium(self) -> tuple[str, int]:
        """The medium's UDP address."""
        return self.host, self.base_port

    @property
    def world(self) -> str:
        return f"tcp://{self.host}:{self.base_port + 1}"

    @property
    def control(self) -> str:
        return f"tcp://{self.host}:{self.base_port + 2}"


def base_port_arg(text: str) -> int:
    """argparse type of ``--base-port``: the medium's UDP port, with base+1 and base+2
    (the world's) also valid ports."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer port, got {text!r}") from None
    if not 1 <= port <= 65535 - 2:
        raise argparse.ArgumentTypeError(
            f"{port}: must be 1..65533 (the world uses base+1 and base+2, ports end at 65535)")
    return port


def add_endpoint_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--base-port", type=base_port_arg, default=DEFAULT_BASE_PORT,
                        help=f"ports: medium = UDP base, world = TCP base+1, world control = TCP base+2 "
                             f"(default {DEFAULT_BASE_PORT})")
    parser.add_argument("--host", default=LOOPBACK,
                        help="host of the medium and world processes (default 127.0.0.1; "
                             "bridges on other hosts point here)")


def rate_arg(text: str) -> int:
    """argparse type of ``--rate``: a sampling rate the default gates can hold."""
    from cellbridge.emulator.firmware.commands import Settings

    try:
        rate = int(text)
        Settings(rate_hz=rate).check(CLOCK_HZ)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc) if "sampling rate" in str(exc)
                                         else f"expected an integer rate in Hz, got {text!r}") from None
    return rate


REPORTING_HELP = (
    "what each bridge reports from power-on: 'periodic' (every sample, the default) or "
    "'event[:THRESHOLD[:HEARTBEAT_MS]]': a sample is sent only when its c1 or c2 moved by more "
    "than THRESHOLD counts (default 0: any change) since the last one sent, or HEARTBEAT_MS "
    "(default 1000) passed; as the SET_REPORTING command (docs/protocol.md). Large skins fit "
    "one 1 Mbit/s gateway link only this way (e.g. --reporting event:40:1000)")


def reporting_arg(text: str) -> ReportingMode:
    """argparse type of ``--reporting``: ``periodic`` or ``event[:THRESHOLD[:HEARTBEAT_MS]]``,
    the two modes of SET_REPORTING, so a skin can boot event-based without a host command."""
    from cellbridge.emulator.firmware.reporting import DEFAULT_HEARTBEAT_MS, MAX_HEARTBEAT_MS, ReportingMode

    parts = text.strip().lower().split(":")
    if parts == ["periodic"]:
        return ReportingMode()
    if parts[0] != "event" or len(parts) > 3:
        raise argparse.ArgumentTypeError(
            f"expected 'periodic' or 'event[:THRESHOLD[:HEARTBEAT_MS]]', got {text!r}")
    try:
        threshold = int(parts[1]) if len(parts) > 1 and parts[1] else 0
        heartbeat = int(parts[2]) if len(parts) > 2 and parts[2] else DEFAULT_HEARTBEAT_MS
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: THRESHOLD and HEARTBEAT_MS must be integers") from None
    if not 0 <= threshold <= 0xFFFF_FFFF:
        raise argparse.ArgumentTypeError(f"{text!r}: THRESHOLD {threshold} must be 0..{0xFFFF_FFFF}")
    if not 0 <= heartbeat <= MAX_HEARTBEAT_MS:
        raise argparse.ArgumentTypeError(f"{text!r}: HEARTBEAT_MS {heartbeat} must be 0..{MAX_HEARTBEAT_MS} "
                                         f"(0: {DEFAULT_HEARTBEAT_MS})")
    return ReportingMode(threshold, heartbeat or DEFAULT_HEARTBEAT_MS)


def reporting_text(mode: ReportingMode) -> str:
    """The ``--reporting`` value that gives ``mode`` (a supervisor passes it on to bridges)."""
    return "periodic" if mode.periodic else f"event:{mode.threshold}:{mode.heartbeat_ms}"


def seconds_arg(text: str) -> float:
    """argparse type of a duration: a finite number of seconds >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, got {text!r}")
    return v


def add_ready_argument(parser: argparse.ArgumentParser) -> None:
    """``--ready-fd``: a pipe on which a process started by ``mesh up`` says it has bound
    its ports (hidden: only a supervisor passes it)."""
    parser.add_argument("--ready-fd", type=int, default=None, help=argparse.SUPPRESS)


def signal_ready(fd: int | None) -> None:
    """Tell the supervisor this process has bound its ports (a line, then EOF); nothing
    without ``--ready-fd``. A supervisor that reads EOF without it knows the start failed."""
    if fd is None:
        return
    try:
        os.write(fd, b"ready\n")
    except OSError:
        pass
    finally:
        os.close(fd)


def endpoints(args: argparse.Namespace) -> Endpoints:
    return Endpoints(args.host, args.base_port)


class StopFlag:
    """Set by SIGINT/SIGTERM; shells check it in their loops and exit cleanly."""

    def __init__(self) -> None:
        self.stopped = False
        signal.signal(signal.SIGTERM, self._set)
        signal.signal(signal.SIGINT, self._set)

    def _set(self, *_: object) -> None:
        self.stopped = True


def die_with_parent() -> None:
    """preexec_fn: the child gets SIGTERM if the process that started it dies (Linux),
    so a supervisor killed with SIGKILL still leaves nothing behind."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def above_the_chips() -> int | None:
    """Under a real-time policy (``chrt -f N cellbridge mesh up``: every process of the
    skin inherits it), raise this process one priority above the one it started with;
    the new priority, or None (not real-time, already at the top, or not permitted).

    For the medium: it stands for the wire, which on a skin carries a frame the instant it
    is sent. At the chips' priority it waited behind them for the CPU, its arbitration of
    who goes first came late, and transmissions that on the wire would have waited
    collided instead: on a 4×4 skin at 100 Hz (``bench/bench_latency.py``, seeds 0–2)
    250–360 retransmissions in 25 s, against 47–88 one priority above them."""
    try:
        got = os.sched_getscheduler(0)
        # ``chrt -R``: the policy comes with SCHED_RESET_ON_FORK or-ed in (kept when set again)
        reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
        policy = got & ~reset
        if policy not in (os.SCHED_FIFO, os.SCHED_RR):
            return None
        up = os.sched_getparam(0).sched_priority + 1
        if up > os.sched_get_priority_max(policy):
            return None
        os.sched_setscheduler(0, got, os.sched_param(up))
    except (OSError, AttributeError):  # not permitted (RLIMIT_RTPRIO), or no sched_* here
        return None
    return up
