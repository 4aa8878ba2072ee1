"""How long each view takes to stop on SIGTERM with a client connected, and what the client gets.

Run: ``.venv/bin/python bench/bench_view_stop.py [--runs N]``.

Each view runs as a real process subscribed to a stand-in daemon
(``bench/fake_daemon.py``); ``web`` and ``foxglove`` have a WebSocket client connected
and reading (a page, a Foxglove app), ``watch`` runs on an 80×24 pty. The time is from
the SIGTERM to the process's exit (``waitpid``), the client's close frame as received.

The machine is shared: the figures move with other load.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import time

from daemon_harness import CLI, free_port
from fake_daemon import FakeDaemon
from pty_terminal import PtyProgram
from timing import table


def stop_server_view(kind: str, fd: FakeDaemon) -> tuple[float, str, int]:
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    port = free_port()
    proc = subprocess.Popen([CLI, kind, "--port", str(port), "--endpoint", fd.endpoints["pub"], "--control",
                             fd.endpoints["control"]], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        assert proc.stdout is not None
        proc.stdout.readline()
        url = f"ws://127.0.0.1:{port}" + ("/ws" if kind == "web" else "")
        with connect(url, subprotocols=["foxglove.sdk.v1"] if kind == "foxglove" else None,  # type: ignore[list-item]
                     open_timeout=10, max_size=1 << 26) as ws:
            fd.publish("health", {"v": 1, "seq": 0, "source": "bench:1", "uptime": 1.0})
            ws.recv(timeout=10)
            t0 = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            close = "none"
            try:
                while True:
                    ws.recv(timeout=30)
            except ConnectionClosed as exc:
                close = str(exc.rcvd.code) if exc.rcvd is not None else "none"
            rc = proc.wait(30)
            return time.monotonic() - t0, close, rc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


def stop_watch(fd: FakeDaemon) -> tuple[float, str, int]:
    watch = PtyProgram([CLI, "watch", "--endpoint", fd.endpoints["pub"], "--control", fd.endpoints["control"]])
    try:
        fd.publish("health", {"v": 1, "seq": 0, "source": "bench:1", "uptime": 1.0})
        watch.wait_for("this view")
        t0 = time.monotonic()
        os.killpg(watch.proc.pid, signal.SIGTERM)
        rc = watch.proc.wait(30)
        took = time.monotonic() - t0
    finally:
        watch.stop()  # (the reader takes every byte written before the exit)
    restored = watch.text().rfind("\x1b[?1049l") > watch.text().rfind("\x1b[?1049h")
    return took, "terminal restored" if restored else "terminal NOT restored", rc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    rows = []
    with FakeDaemon() as fd:
        for kind in ("web", "foxglove", "watch"):
            runs = [stop_watch(fd) if kind == "watch" else stop_server_view(kind, fd) for _ in range(a.runs)]
            times = sorted(t for t, _, _ in runs)
            rows.append([kind, len(runs), f"{times[len(times) // 2]:.2f}", f"{times[-1]:.2f}",
                         ", ".join(sorted({c for _, c, _ in runs})), ", ".join(sorted({str(r) for _, _, r in runs}))])
    table(f"SIGTERM to exit, a client connected ({os.getloadavg()[0]:.1f} load average at the end)",
          ["view", "runs", "p50 s", "max s", "client got (close code)", "exit status"], rows)


if __name__ == "__main__":
    main()
