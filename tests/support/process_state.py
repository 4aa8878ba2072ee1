"""Whether a process has ended, read from /proc (a zombie counts as ended: its parent,
this test process perhaps, has not reaped it yet, but it runs no more)."""

from __future__ import annotations

import os
import subprocess
import time


def gone(pid: int) -> bool:
    """``pid`` is not running (no such process, or a zombie)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def until_gone(pid: int, limit: float = 10.0) -> bool:
    """Wait up to ``limit`` s for ``pid`` to end; whether it did."""
    end = time.monotonic() + limit
    while not gone(pid) and time.monotonic() < end:
        time.sleep(0.02)
    return gone(pid)


def rss_mib(pid: int) -> int:
    """``pid``'s resident memory in MiB (0: gone, or not readable)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) // 1024
    except OSError:
        pass
    return 0


def first_stderr_line(proc: subprocess.Popen[bytes], limit: float = 30.0) -> bytes:
    """What ``proc`` wrote on its stderr (a pipe) until its first full line, ``limit`` s at
    most, or until it ended: a command that says something and waits on is read without
    blocking on the rest. Leaves the pipe non-blocking."""
    assert proc.stderr is not None
    os.set_blocking(proc.stderr.fileno(), False)
    said = b""
    end = time.monotonic() + limit
    while b"\n" not in said and time.monotonic() < end and proc.poll() is None:
        said += proc.stderr.read() or b""
        time.sleep(0.1)
    return said
