"""The demo's skin and daemon do not outlive the demo, however it ends."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

CHILD = """
import time
from cellbridge.demo import _group
with _group(["sleep", "60"]) as p:
    print(p.pid, flush=True)
    time.sleep(60)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_demo_killed_outright_takes_its_processes_with_it() -> None:
    """SIGKILL (a test's timeout, the OOM killer): no ``finally`` runs, and the children
    live in their own sessions, out of reach of a kill of the demo's group."""
    demo = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True, start_new_session=True)
    child = -1
    try:
        assert demo.stdout is not None
        child = int(demo.stdout.readline())
        assert _alive(child)
        os.kill(demo.pid, signal.SIGKILL)
        demo.wait()
        end = time.monotonic() + 10.0
        while _alive(child) and time.monotonic() < end:
            time.sleep(0.02)
        assert not _alive(child), "the demo's child outlived it"
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        if child > 0 and _alive(child):
            os.kill(child, signal.SIGKILL)
        if demo.stdout is not None:
            demo.stdout.close()
