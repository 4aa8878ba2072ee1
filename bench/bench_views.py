"""The views' figures: press to pixels on the page, CPU of each view, terminal refreshes over a slow pipe.

Run: ``.venv/bin/python bench/bench_views.py [--quick]`` (needs Debian's ``chromium`` and
``tmux``; ``make test`` installs them as root).

Except in 1a, the skin is synthesized gateway traffic (``bench/daemon_traffic.py``) written
into a pty in real time by a thread of this script; the daemon reads that pty as it would a
gateway's serial line, and each view is a real process subscribed to the daemon.

1. **Press to pixels** (web page), twice:
   a. *from the world*: an emulated 4×4 skin in real processes (``cellbridge mesh up``, one
      process per bridge, 100 Hz, event-based reporting as ``cellbridge demo`` runs it),
      its daemon, ``cellbridge web`` and a headless Chromium page. The world process is
      asked for presses (its control socket, as ``cellbridge press`` does) that start a
      little ahead, and answers with the monotonic instant each one starts; the latency is
      from that instant to the first animation frame after the page drew the pressed
      element touched (``performance.timeOrigin + now()`` in a ``requestAnimationFrame``
      after the draw; both clocks are this host's, the monotonic one mapped to the wall
      clock in this process). It holds all of it: the bridge's next gate (up to one sample
      period), its report and the mesh hops, the serial line, the daemon, the view's
      update rate (30/s) and the browser's paint.
   b. *from the serial line*: a press switched on and off again and again in synthesized
      gateway traffic; from the write of the first pressed sample's bytes to the gateway
      line to the page's paint, as above (the host side alone).
2. **CPU of each view**: user+system CPU seconds of the view's process over a window,
   as % of one core, at 250 Hz on a 4×4 skin and at 100 Hz on a 16×16 skin, each view
   with a consumer attached (watch: tmux 80×24; web: one headless Chromium page, whose
   own CPU is shown apart; foxglove: a protocol client subscribed to every channel).
3. **Terminal refreshes over a slow pipe**: ``cellbridge watch`` on a pty this script
   reads at a capped bandwidth (a token bucket: SSH over a slow link), a press sliding
   across a 4×4 skin at 100 Hz; counted are the frames that reach the terminal whole
   (Textual brackets each frame in synchronized-output marks, which this "terminal"
   says it supports).

The machine is shared: CPU and latency figures move with other load.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import struct
import subprocess
import sys
import tempfile
import termios
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from browser import CHROMIUM, browser
from live_skin import Collector, calibrated, live_skin
from timing import table
from view_harness import (
    CLI,
    PRESS,
    Client,
    daemon,
    fed_skin,
    free_port,
    skin_config,
    stop_session,
    view_process,
    wait_ready,
)


def cpu_seconds(pids: list[int]) -> float:
    """utime + stime of these processes (and their threads), in seconds."""
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
        except (OSError, IndexError):
            pass
    return total / os.sysconf("SC_CLK_TCK")


def session_pids(sid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-s", str(sid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split()]


def wait_line(proc: subprocess.Popen[bytes], timeout: float = 30.0) -> str:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    if not ready:
        raise RuntimeError("the view printed nothing")
    return proc.stdout.readline().decode()


def pct(x: float) -> str:
    return f"{x * 100:.1f} %"


# ---- 1. press to pixels ----------------------------------------------------------------------

WORLD_PRESS = (0.080, 0.080, 3.0, 0.020)  # x, y (m), force (N), diameter (m): centred on bridge 11 of the 4x4 grid


def press_in_world(control: str, start_in: float, duration: float) -> float:
    """Ask the emulated skin's world for a press starting ``start_in`` s from now; its start as wall time (s)."""
    import msgpack
    import zmq

    x, y, force, diameter = WORLD_PRESS
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.REQ)
    sock.linger = 0
    sock.connect(control)
    try:
        sock.send(msgpack.packb({"start": start_in, "duration": duration, "position": [x, y], "force": force,
                                 "diameter": diameter}))
        if not sock.poll(5000):
            raise RuntimeError(f"the world at {control} did not answer")
        answer = msgpack.unpackb(sock.recv())
    finally:
        sock.close()
    if not answer.get("ok"):
        raise RuntimeError(f"the world refused the press: {answer.get('error')}")
    return float(answer["start"]) + (time.time() - time.monotonic())  # the world's monotonic clock -> wall


def world_press_to_pixels(tmp: Path, presses: int, reporting: str) -> tuple[list[float], int]:
    """(latency s of each press that reached the page, presses asked): world press -> page painted."""
    on, off = 0.4, 0.8  # s pressed, s released (the element untouched again before the next)
    starts: list[float] = []
    with live_skin(tmp, 4, 4, reporting=reporting) as skin:
        port = free_port()
        health = Collector(skin.pub, (b"health",))
        try:
            with skin.daemon(skin.daemon_config()), \
                    view_process(["web", "--port", str(port), "--endpoint", skin.pub, "--control", skin.control],
                                 stdout=subprocess.PIPE) as web, browser(tmp) as page:
                wait_line(web)
                health.pump(180, until=calibrated(skin.elements))
                page.navigate(f"http://127.0.0.1:{port}/")
                page.wait_for("cellbridge.frame && cellbridge.frame.cells.length === 16", what="the skin")
                press_in_world(skin.world_control, 0.2, on)  # a first press: kernels compile, routes settle
                time.sleep(on + off + 1.0)
                for _ in range(presses):
                    starts.append(press_in_world(skin.world_control, 0.2, on))
                    time.sleep(0.2 + on + off)
                time.sleep(1.0)
                paints = page.evaluate("cellbridge.paints")
        finally:
            health.close()
    return touch_latencies(starts, paints, on + off), len(starts)


def touch_latencies(starts: list[float], paints: list[list[Any]], period: float) -> list[float]:
    """For each press start (wall s), the delay to the first paint of a touched skin after it,
    counted only where the page showed no touch at the start (the previous press had ended)."""
    marks = [(t / 1e3, bool(touched)) for t, touched in paints]
    lat = []
    for t0 in starts:
        before = [touched for t, touched in marks if t < t0]
        if before and before[-1]:
            continue
        shown = [t for t, touched in marks if touched and t >= t0]
        if shown and shown[0] - t0 < period:
            lat.append(shown[0] - t0)
    return lat


def press_to_pixels(tmp: Path, presses: int) -> list[float]:
    on, off = 30, 40  # slots (100 Hz): 0.3 s pressed, 0.4 s released

    def pattern(k: int) -> tuple[float, float, float, float] | None:
        return PRESS if k % (on + off) < on else None

    with fed_skin(tmp, rows=4, cols=4) as (pty, feeder):
        cfg, ep = skin_config(tmp, pty)
        client = Client(ep, (b"health", b"contact"))
        port = free_port()
        try:
            with daemon(cfg, tmp / "daemon.log"), \
                    view_process(["web", "--port", str(port), "--endpoint", ep["pub"], "--control", ep["control"]],
                                 stdout=subprocess.PIPE) as web, browser(tmp) as page:
                wait_line(web)
                wait_ready(client)
                page.navigate(f"http://127.0.0.1:{port}/")
                page.wait_for("cellbridge.frame && cellbridge.frame.cells.length === 16", what="the skin")
                feeder.onsets.clear()
                feeder.press(pattern)
                time.sleep(presses * (on + off) / 100 + 1.0)
                feeder.press(None)
                paints = page.evaluate("cellbridge.paints")
        finally:
            client.close()
    onsets = [t for _, t in feeder.onsets][1:]  # the first may meet kernels still compiling
    lat = []
    for t0 in onsets:
        shown = [t / 1e3 for t, touched in paints if touched and t / 1e3 >= t0]
        if shown and shown[0] - t0 < (on + off) / 100:
            lat.append(shown[0] - t0)
    return lat


# ---- 2. CPU of each view -----------------------------------------------------------------------

class FoxgloveReader(threading.Thread):
    """A Foxglove client subscribed to every channel, reading all it gets."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        from cellbridge.views.foxglove import TOPICS
        from foxglove_client import FoxgloveClient

        self.client = FoxgloveClient(url)
        self.client.wait_channels(list(TOPICS.values()))
        for t in TOPICS.values():
            self.client.subscribe(t)
        self.messages = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self.client.ws.recv(timeout=0.5)
                self.messages += 1
            except TimeoutError:
                continue
            except Exception:
                return

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.client.close()


def view_cpu(tmp: Path, kind: str, rows: int, cols: int, rate: float, window: float) -> dict[str, Any]:
    with fed_skin(tmp, rows=rows, cols=cols, rate=rate) as (pty, feeder):
        cfg, ep = skin_config(tmp, pty)
        client = Client(ep, (b"health",))
        args = ["--endpoint", ep["pub"], "--control", ep["control"]]
        out: dict[str, Any] = {}
        try:
            with daemon(cfg, tmp / "daemon.log") as d:
                wait_ready(client, 60)
                feeder.press()
                if kind == "watch":
                    sock = str(tmp / "tmux.sock")
                    subprocess.run(["tmux", "-S", sock, "new-session", "-d", "-s", "v", "-x", "80", "-y", "24",
                                    "-e", "COLORTERM=truecolor", f"{CLI} watch {' '.join(args)}"], check=True)
                    try:
                        time.sleep(3)
                        pane = int(subprocess.run(["tmux", "-S", sock, "display", "-p", "-t", "v", "#{pane_pid}"],
                                                  capture_output=True, text=True).stdout)
                        out.update(_measure([pane], window, d.pid))
                    finally:
                        subprocess.run(["tmux", "-S", sock, "kill-server"], capture_output=True)
                elif kind == "web":
                    port = free_port()
                    with view_process(["web", "--port", str(port), *args], stdout=subprocess.PIPE) as web, \
                            browser(tmp) as page:
                        wait_line(web)
                        page.navigate(f"http://127.0.0.1:{port}/")
                        page.wait_for("cellbridge.frame && cellbridge.frame.cells.length", what="the skin")
                        time.sleep(2)
                        chromium = [p for p in map(int, subprocess.run(["pgrep", "-f", "chromium-profile"],
                                    capture_output=True, text=True).stdout.split())]
                        f0 = page.evaluate("cellbridge.frames")
                        out.update(_measure([web.pid], window, d.pid, extra=chromium))
                        out["page_fps"] = (page.evaluate("cellbridge.frames") - f0) / window
                else:
                    port = free_port()
                    with view_process(["foxglove", "--port", str(port), *args], stdout=subprocess.PIPE) as fx:
                        wait_line(fx)
                        reader = FoxgloveReader(f"ws://127.0.0.1:{port}")
                        reader.start()
                        try:
                            time.sleep(2)
                            m0 = reader.messages
                            out.update(_measure([fx.pid], window, d.pid))
                            out["fox_msgs"] = (reader.messages - m0) / window
                        finally:
                            reader.close()
                out["feeder_late"] = feeder.late
        finally:
            client.close()
    return out


def _measure(pids: list[int], window: float, daemon_pid: int, extra: list[int] | None = None) -> dict[str, float]:
    c0, d0, e0 = cpu_seconds(pids), cpu_seconds(session_pids(daemon_pid)), cpu_seconds(extra or [])
    t0 = time.monotonic()
    time.sleep(window)
    dt = time.monotonic() - t0
    return {"view": (cpu_seconds(pids) - c0) / dt, "daemon": (cpu_seconds(session_pids(daemon_pid)) - d0) / dt,
            "extra": (cpu_seconds(extra or []) - e0) / dt}


# ---- 3. terminal refreshes over a slow pipe ----------------------------------------------------

SYNC_QUERY, SYNC_REPLY, SYNC_END = b"\x1b[?2026$p", b"\x1b[?2026;2$y", b"\x1b[?2026l"


def slow_terminal(tmp: Path, bandwidth: float | None, window: float) -> dict[str, float]:
    """Frames/s and bytes/s that reach a terminal read at ``bandwidth`` bit/s (None: as fast as it comes)."""
    def sliding(k: int) -> tuple[float, float, float, float]:
        x = 0.02 + 0.12 * (k % 200) / 200  # across the 4×4 skin in 2 s
        return (x, 0.05, 2.0, 0.012)

    with fed_skin(tmp, rows=4, cols=4) as (pty, feeder):
        cfg, ep = skin_config(tmp, pty)
        client = Client(ep, (b"health",))
        try:
            with daemon(cfg, tmp / "daemon.log"):
                wait_ready(client)
                feeder.press(sliding)
                master, slave = os.openpty()
                termios_size = struct.pack("HHHH", 24, 80, 0, 0)
                import fcntl

                fcntl.ioctl(slave, termios.TIOCSWINSZ, termios_size)
                env = dict(os.environ, TERM="xterm-256color", COLORTERM="truecolor")
                proc = subprocess.Popen([CLI, "watch", "--endpoint", ep["pub"], "--control", ep["control"]],
                                        stdin=slave, stdout=slave, stderr=slave, env=env, start_new_session=True)
                os.close(slave)
                try:
                    return _read_terminal(master, bandwidth, window)
                finally:
                    stop_session(proc)
                    os.close(master)
        finally:
            client.close()


def _read_terminal(master: int, bandwidth: float | None, window: float) -> dict[str, float]:
    warmup = 3.0
    start = time.monotonic()
    frames = nbytes = 0
    tail = b""
    budget, last = 0.0, start
    counting = False
    t_count = start
    while True:
        now = time.monotonic()
        if not counting and now - start >= warmup:
            counting, t_count, frames, nbytes = True, now, 0, 0
        if counting and now - t_count >= window:
            break
        chunk = 4096
        if bandwidth is not None:
            budget = min(budget + (now - last) * bandwidth / 8, 4096.0)
            last = now
            if budget < 256:
                time.sleep((256 - budget) * 8 / bandwidth)
                continue
            chunk = int(budget)
        ready, _, _ = select.select([master], [], [], 0.1)
        if not ready:
            continue
        try:
            data = os.read(master, chunk)
        except OSError:
            break
        if bandwidth is not None:
            budget -= len(data)
        buf = tail + data
        if SYNC_QUERY in buf:
            os.write(master, SYNC_REPLY)
        frames += buf.count(SYNC_END) - tail.count(SYNC_END)
        nbytes += len(data)
        tail = buf[-16:]
    dt = time.monotonic() - t_count
    return {"fps": frames / dt, "bytes_s": nbytes / dt, "bytes_frame": nbytes / frames if frames else float("nan")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer presses, shorter windows")
    ap.add_argument("--only-press", action="store_true", help="part 1 only (press to pixels)")
    ap.add_argument("--reporting", default="event:40",
                    help="the emulated skin's reporting in 1a, as 'cellbridge mesh up --reporting' "
                         "(default event:40, as 'cellbridge demo')")
    args = ap.parse_args()
    if CHROMIUM is None or subprocess.run(["which", "tmux"], capture_output=True).returncode:
        print("bench_views: needs Debian's chromium and tmux (make test installs them as root)")
        return 1
    presses, window = (10, 4.0) if args.quick else (40, 10.0)
    with tempfile.TemporaryDirectory(prefix="bench-views-") as td:
        tmp = Path(td)
        load = os.getloadavg()
        print(f"load average at start: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} ({os.cpu_count()} cores)")
        (tmp / "world").mkdir()
        (tmp / "lat").mkdir()
        world, asked = world_press_to_pixels(tmp / "world", presses, args.reporting)
        wlat = np.array(world) * 1e3
        print(f"1a measured: {len(wlat)} of {asked} presses; ms: {sorted(np.round(wlat, 1).tolist())}", flush=True)
        lat = np.array(press_to_pixels(tmp / "lat", presses)) * 1e3
        prow = (lambda name, x: [name, len(x), f"{np.percentile(x, 50):.1f}", f"{np.percentile(x, 99):.1f}",
                                 f"{x.max():.1f}"] if len(x) else [name, 0, "-", "-", "-"])
        table("1. press to pixels, web page (4x4 skin at 100 Hz)",
              ["path", "presses", "p50 ms", "p99 ms", "max ms"],
              [prow(f"a. press starts in the world ({args.reporting} reporting, real processes) -> page painted",
                    wlat),
               prow("b. pressed sample's bytes on the gateway line -> page painted", lat)])
        if len(wlat) < asked:
            print(f"   (a: {asked - len(wlat)} of {asked} presses not counted: the page still showed the previous "
                  f"touch at the press's start, or showed none within {1.2:.1f} s)")
        if args.only_press:
            print(json.dumps({"press_to_pixels_ms": _quantiles(lat), "world_press_to_pixels_ms": _quantiles(wlat),
                              "load": load[0]}))
            return 0
        rows = []
        for rows_, cols, rate in ((4, 4, 250.0), (16, 16, 100.0)):
            for kind in ("watch", "web", "foxglove"):
                sub = tmp / f"cpu-{kind}-{rows_}"
                sub.mkdir()
                r = view_cpu(sub, kind, rows_, cols, rate, window)
                note = {"web": f"page {r.get('page_fps', 0):.0f} frames/s; Chromium {pct(r['extra'])}",
                        "foxglove": f"{r.get('fox_msgs', 0):.0f} messages/s to the client",
                        "watch": "tmux 80x24"}[kind]
                rows.append([f"{rows_}x{cols} at {rate:.0f} Hz", kind, pct(r["view"]), pct(r["daemon"]), note])
        table(f"2. CPU of each view (% of one core over {window:.0f} s)",
              ["skin", "view", "view CPU", "daemon CPU", "consumer"], rows)
        trows = []
        for bw in (None, 1_000_000.0, 256_000.0, 64_000.0):
            sub = tmp / f"term-{bw}"
            sub.mkdir()
            r = slow_terminal(sub, bw, window)
            trows.append(["unlimited" if bw is None else f"{bw / 1e3:.0f} kbit/s", f"{r['fps']:.1f}",
                          f"{r['bytes_s'] / 1e3:.1f}", f"{r['bytes_frame']:.0f}"])
        table("3. cellbridge watch refreshes reaching an 80x24 terminal (4x4 skin, press sliding, 100 Hz)",
              ["pipe", "frames/s", "kB/s", "bytes/frame"], trows)
    print(json.dumps({"press_to_pixels_ms": _quantiles(lat), "world_press_to_pixels_ms": _quantiles(wlat),
                      "load": load[0]}))
    return 0


def _quantiles(x: np.ndarray) -> dict[str, float]:
    return {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)), "n": int(len(x))} if len(x) \
        else {"n": 0}


if __name__ == "__main__":
    sys.exit(main())
