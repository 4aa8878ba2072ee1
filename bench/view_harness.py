"""A live daemon fed by a known press, for the views' tests and bench.

A :class:`Feeder` thread writes synthesized gateway traffic (``daemon_traffic.GridFrames``:
HELLO, BEACON, quiet samples for the baseline, then a press) into a pty in real time;
the daemon reads it as it would a gateway's serial line. The press is held, or
switched on and off (the bench's press-to-pixels latency), and the feeder notes when
the first pressed sample's bytes were written.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from daemon_harness import CLI, Client, Pty, daemon, free_port, stop_session, write_config
from daemon_traffic import GridFrames

PRESS = (0.040, 0.022, 2.0, 0.010)  # across the seam of bridges 2 and 5 of a 3×3 skin
PRESSED = (2, 5)
BASELINE_SLOTS = 30


def skin_config(tmp_path: Path, pty: Pty, endpoints: dict[str, str] | None = None,
                **sections: dict[str, object]) -> tuple[Path, dict[str, str]]:
    """A daemon config reading the feeder's pty (same endpoints again for a restart)."""
    cfg = tmp_path / "daemon.toml"
    extra: dict[str, dict[str, object]] = {"calibration": {"n_baseline": 10}}
    if endpoints is not None:
        extra["pub"], extra["control"] = {"endpoint": endpoints["pub"]}, {"endpoint": endpoints["control"]}
    extra.update(sections)
    ep = write_config(cfg, [{"name": "gw", "url": pty.link}], **extra)
    return cfg, ep


class Feeder(threading.Thread):
    """Gateway traffic of ``skin`` into ``pty`` at the skin's rate, in real time.

    Quiet until :meth:`press` is called (a daemon takes its baseline from the first
    samples it reads: press only once it is ready). ``pattern(k)`` gives the press of
    the k-th slot since then, or None. HELLOs and BEACONs are repeated every second, so
    a daemon started (or restarted) while the feeder runs learns the layout."""

    def __init__(self, pty: Pty, skin: GridFrames) -> None:
        super().__init__(daemon=True)
        self.pty, self.skin = pty, skin
        self.pattern: Callable[[int], tuple[float, float, float, float] | None] | None = None
        self.since = 0
        self.k = 0
        self.stop_event = threading.Event()
        self.onsets: list[tuple[int, float]] = []  # (slot, wall time its bytes were written) of each press onset
        self.late = 0  # slots written more than one period late (the feeder could not keep up)
        self.unread = 0  # writes given up after 30 s with nobody reading the line

    def press(self, pattern: Callable[[int], tuple[float, float, float, float] | None] | None = lambda k: PRESS
              ) -> None:
        """Press from the next slot on (``None``: quiet again)."""
        self.since, self.pattern = self.k, pattern

    def run(self) -> None:
        sk, period = self.skin, 1.0 / self.skin.rate
        t0 = time.monotonic()
        was = None
        while not self.stop_event.is_set():
            k = self.k
            pattern = self.pattern
            press = pattern(k - self.since) if pattern is not None else None
            data = sk.slot(k, press)
            if k % int(sk.rate) == 0:
                data = sk.hellos() + sk.beacons() + data
            try:
                self.pty.write(data, limit=30.0)
            except AssertionError:  # nobody reads the line (a daemon stopping, or between two runs)
                self.unread += 1  # its bytes are lost, as a device's are: the feeder goes on
            except OSError:
                return
            if press is not None and was is None:
                self.onsets.append((k, time.time()))
            was = press
            self.k = k + 1
            delay = t0 + self.k * period - time.monotonic()
            if delay > 0:
                self.stop_event.wait(delay)
            elif delay < -period:
                self.late += 1

    def stop(self) -> None:
        self.stop_event.set()
        self.join(5)


def wait_ready(client: Client, timeout: float = 30.0) -> None:
    """Until the daemon has every element's baseline (the feeder may press from then on)."""
    client.request({"v": 1, "cmd": "ping"}, timeout)
    while client.recv(0.0) is not None:  # what an earlier daemon published is still queued here
        pass
    client.wait_for("health", lambda m: (m.get("layout", {}).get("calibration", {}).get("ready", 0)
                                         >= m.get("layout", {}).get("elements", 1) > 0), timeout)


@contextmanager
def fed_skin(tmp_path: Path, rows: int = 3, cols: int = 3, rate: float = 100.0) -> Iterator[tuple[Pty, Feeder]]:
    pty = Pty(tmp_path / "gw")
    feeder = Feeder(pty, GridFrames(rows=rows, cols=cols, rate=rate))
    feeder.start()
    try:
        yield pty, feeder
    finally:
        feeder.stop()
        pty.close()


@contextmanager
def view_process(argv: list[str], **kw: object) -> Iterator[subprocess.Popen[bytes]]:
    """A view as a real process in its own session; always stopped (TERM, then KILL)."""
    proc = subprocess.Popen([CLI, *argv], start_new_session=True, **kw)  # type: ignore[call-overload]  # the caller's Popen keywords
    try:
        yield proc
    finally:
        stop_session(proc)


__all__ = ["CLI", "PRESS", "PRESSED", "Client", "Feeder", "daemon", "fed_skin", "free_port", "skin_config",
           "stop_session", "view_process", "wait_ready"]
