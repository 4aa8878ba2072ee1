"""The suite's process guard (tests/conftest.py ``_no_process_outlives_its_module``) sees
what a module's tests leave running: a grandchild under a child still alive, and a
daemon that double-forked and called ``setsid`` itself (its parent gone, its session
its own)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import conftest

DAEMONISE = """
import os, sys, time
if os.fork():
    os._exit(0)
os.setsid()
if os.fork():
    os._exit(0)
os.write(int(sys.argv[1]), str(os.getpid()).encode())
time.sleep(60)
"""


def _end(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        return
    end = time.monotonic() + 5
    while time.monotonic() < end:
        try:
            if os.waitpid(pid, os.WNOHANG)[0]:
                return  # adopted by this process (a subreaper): reaped
        except ChildProcessError:  # not ours: init reaps it
            pass
        try:
            with open(f"/proc/{pid}/stat", "rb") as f:
                if f.read().rsplit(b")", 1)[1].split()[0] in (b"Z", b"X"):
                    return
        except OSError:
            return
        time.sleep(0.01)


def test_the_guard_sees_a_daemon_that_double_forked_and_called_setsid() -> None:
    """Its parent exited at once and its session is its own: by the parent, the group and
    the session a test's process led, nothing led to it, and it outlived the suite."""
    r, w = os.pipe()
    try:
        subprocess.run([sys.executable, "-c", DAEMONISE, str(w)], pass_fds=(w,), timeout=30, check=True)
        os.close(w)
        w = -1
        pid = int(os.read(r, 32))
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)
    try:
        assert pid in conftest._alive_descendants(), "a daemonised grandchild was not seen"
    finally:
        _end(pid)


def test_the_guard_sees_a_grandchild_under_a_child_still_running() -> None:
    """Killing the child alone (what the guard does to what it finds) leaves the grandchild
    running: it must be found, and killed, too."""
    proc = subprocess.Popen(["sh", "-c", "sleep 60 & echo $!; wait"], stdout=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        grandchild = int(proc.stdout.readline())
        found = conftest._alive_descendants()
        assert proc.pid in found and grandchild in found, (proc.pid, grandchild, found)
    finally:
        proc.kill()
        proc.wait(5)
        _end(grandchild)


def test_the_guard_waits_for_a_process_that_is_ending_and_reports_one_that_is_not() -> None:
    """A grandchild left to exit by itself once its parent was stopped (a daemon's contact
    worker) is ending, not left running: the guard gives it ``EXIT_GRACE`` to end. One that
    stays is still reported after that wait."""
    ending = subprocess.Popen(["sleep", "0.3"])
    staying = subprocess.Popen(["sleep", "60"])
    try:
        t0 = time.monotonic()
        left = conftest._left_after(3.0)
        assert ending.pid not in left, left  # ended within the grace, and was not reported
        assert staying.pid in left, left
        assert time.monotonic() - t0 >= 2.9  # it waited the grace out for the one staying
    finally:
        for p in (ending, staying):
            p.kill()
            p.wait(5)
