"""What ``cellbridge ros2`` adds: latency over the ZeroMQ contact, and its CPU.

Run: ``.venv/bin/python bench/bench_ros2.py [--quick]``.

The skin is synthesized gateway traffic (``bench/daemon_traffic.py``) written into a pty in
real time by a thread of this script, the daemon reads that pty as a gateway's serial
line, and ``cellbridge ros2`` is a real process subscribed to the daemon. This script is
two subscribers at once, each in a thread of its own that stamps what it receives with
the monotonic clock: one on the daemon's ZeroMQ ``contact`` topic, one a DDS participant
(loopback, its own domain) reading every ROS 2 topic of ``cellbridge ros2``. A press is
held on the skin, so every estimate publishes a contact.

1. **Added latency** (the script then reads contacts alone, so that its own thread decoding
   the large messages does not delay the stamps): for each contact message, the time from its arrival on ZeroMQ to the
   arrival of the ``TactileContacts`` of the same skin frame (its header stamp is the
   message's ``t_sample``) over DDS: what the bridge to ROS 2 adds (a ZeroMQ hop, the
   conversion, CDR, DDS on loopback) on top of what any ZeroMQ subscriber sees.
   Beside it, the share of that window the bridge's main thread spent on a CPU and
   runnable but waiting for one (the kernel's schedstat): a loaded machine's delays.
2. **CPU**: user+system CPU seconds of the ``cellbridge ros2`` process over a window, as %
   of one core, and what it published per second, on a 4×4 skin at 250 Hz and a 16×16
   skin at 100 Hz.

The machine is shared: CPU and latency figures move with other load.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zmq
from cyclonedds.util import duration

from ros2_peer import Peer
from timing import table
from view_harness import PRESS, Client, daemon, fed_skin, skin_config, view_process, wait_ready

NS = "/bench"


def sched_seconds(pid: int) -> tuple[float, float]:
    """The main thread's (on a CPU, waiting for one while runnable), in seconds: the kernel's
    schedstat. ``cellbridge ros2`` does its work in that thread; a contact held up while it
    waited for a CPU is the machine's load, not the bridge's work."""
    on, wait, _ = Path(f"/proc/{pid}/schedstat").read_text().split()
    return int(on) / 1e9, int(wait) / 1e9


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), in seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class ZmqContacts(threading.Thread):
    """Arrival (monotonic) of every contact message, by its t_sample in ns."""

    def __init__(self, endpoint: str) -> None:
        super().__init__(daemon=True)
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.SUB)
        self.sock.linger = 0
        self.sock.rcvhwm = 0
        self.sock.subscribe(b"contact")
        self.sock.connect(endpoint)
        self.arrived: dict[int, float] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            if self.sock.poll(100):
                _, payload = self.sock.recv_multipart()
                now = time.monotonic()
                m = msgpack.unpackb(payload, strict_map_key=False)
                if m.get("contacts"):
                    self.arrived.setdefault(round(m["t_sample"] * 1e9), now)

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.ctx.destroy(linger=0)


class DdsTopics(threading.Thread):
    """Arrival of every sample of every topic; contacts' arrivals by their header stamp."""

    def __init__(self, peer: Peer, block: bool) -> None:
        super().__init__(daemon=True)
        self.peer = peer
        self.block = block  # wait in the DDS library for contacts (read alone), else poll every topic
        self.counts: dict[str, int] = {t: 0 for t in peer.readers}
        self.readers = list(peer.readers.items())
        self.contacts: dict[int, float] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        readers = self.readers
        contacts = self.peer.readers[f"{NS}/contacts"]
        while not self.stop.is_set():
            got = contacts.take_iter(timeout=duration(milliseconds=50)) if self.block else contacts.take(N=10_000)
            if not self.block:
                time.sleep(0.001)
            for s in got:
                now = time.monotonic()
                self.counts[f"{NS}/contacts"] += 1
                if s.contacts:
                    st = s.contacts[0].header.stamp
                    self.contacts.setdefault(st.sec * 1_000_000_000 + st.nanosec, now)
                if self.stop.is_set():  # (take_iter goes on while samples keep coming)
                    break
            for topic, reader in readers:
                if reader is not contacts:
                    self.counts[topic] += len(reader.take(N=10_000))

    def close(self) -> None:
        self.stop.set()
        self.join()  # before any reader goes


def run_case(tmp: Path, rows: int, cols: int, rate: float, window: float) -> dict[str, Any]:
    domain = random.randrange(100, 230)
    press = PRESS  # across the seam of two elements
    with fed_skin(tmp, rows=rows, cols=cols, rate=rate) as (pty, feeder):
        cfg, ep = skin_config(tmp, pty)
        client = Client(ep, (b"health", b"contact"))
        peer = Peer(domain)
        try:
            peer.subscribe(f"{NS}/contacts", "tactile_msgs/msg/TactileContacts", reliable=True)
            peer.subscribe(f"{NS}/tactile_state", "tactile_msgs/msg/TactileState", reliable=False)
            peer.subscribe(f"{NS}/markers", "visualization_msgs/msg/MarkerArray", reliable=True)
            peer.subscribe(f"{NS}/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", reliable=True)
            with daemon(cfg, tmp / "daemon.log") as d:
                wait_ready(client, 120)
                n = rows * cols  # every element placed and calibrated (a 16x16 layout grows over a few HELLOs:
                client.wait_for("health", lambda m: m.get("layout", {}).get("elements") == n  # a press in a
                                and m["layout"].get("calibration", {}).get("ready", 0) >= n, 120)  # baseline is none)
                feeder.press(lambda k: press)
                client.wait_for("contact", lambda m: len(m["contacts"]) >= 1, timeout=120)
                with view_process(["ros2", "--endpoint", ep["pub"], "--control", ep["control"], "--domain",
                                   str(domain), "--namespace", NS, "--diagnostics-topic", f"{NS}/diagnostics"],
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL) as proc:
                    proc.stdout.readline()  # type: ignore[union-attr]  # ready
                    dq = DdsTopics(peer, block=False)
                    dq.start()
                    try:
                        time.sleep(2.0)  # joined, layout known
                        c0, d0, t0 = cpu_seconds(proc.pid), cpu_seconds(d.pid), time.monotonic()
                        n0 = dict(dq.counts)
                        time.sleep(window)
                        dt = time.monotonic() - t0
                        cpu, dcpu = (cpu_seconds(proc.pid) - c0) / dt, (cpu_seconds(d.pid) - d0) / dt
                        rates = {t.rsplit("/", 1)[1]: (dq.counts[t] - n0[t]) / dt for t in dq.counts}
                    finally:
                        dq.close()
                    # latency: contacts alone (this script's GIL spent deserialising a 16x16 state or
                    # picture would delay the stamps it takes)
                    for topic in [t for t in peer.readers if not t.endswith("/contacts")]:
                        peer.readers.pop(topic).__del__()
                    zq, dq = ZmqContacts(ep["pub"]), DdsTopics(peer, block=True)
                    zq.start()
                    dq.start()
                    s0, t0 = sched_seconds(proc.pid), time.monotonic()
                    try:
                        time.sleep(window)
                        s1, dt = sched_seconds(proc.pid), time.monotonic() - t0
                    finally:
                        zq.close()
                        dq.close()
                    on_cpu, runnable = (s1[0] - s0[0]) / dt, (s1[1] - s0[1]) / dt
                    lat = np.array([dq.contacts[k] - t for k, t in zq.arrived.items() if k in dq.contacts]) * 1e3
                    unmatched = sum(1 for k in zq.arrived if k not in dq.contacts)
        finally:
            peer.close()
            client.close()
    return {"cpu": cpu, "daemon_cpu": dcpu, "rates": rates, "lat": lat, "unmatched": unmatched,
            "on_cpu": on_cpu, "runnable": runnable,
            "late": feeder.late}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter windows")
    args = ap.parse_args()
    window = 5.0 if args.quick else 15.0
    load = os.getloadavg()
    print(f"load average at start: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} ({os.cpu_count()} cores)")
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-ros2-") as td:
        for rows, cols, rate in ((4, 4, 250.0), (16, 16, 100.0)):
            sub = Path(td) / f"{rows}x{cols}"
            sub.mkdir()
            try:
                results.append(((rows, cols, rate), run_case(sub, rows, cols, rate, window)))
            except AssertionError as exc:  # a daemon starved on a busy machine estimated no contact
                print(f"{rows}x{cols} at {rate:.0f} Hz: not measured ({exc})", flush=True)
    q = (lambda x, p: f"{np.percentile(x, p):.2f}" if len(x) else "-")
    table("1. added latency: contact on ZeroMQ -> the same frame's TactileContacts over DDS (ms)",
          ["skin", "contacts", "p50", "p99", "max", "not matched", "ros2 on a CPU", "ros2 waiting for one"],
          [[f"{r}x{c} at {hz:.0f} Hz", len(x["lat"]), q(x["lat"], 50), q(x["lat"], 99),
            f"{x['lat'].max():.2f}" if len(x["lat"]) else "-", x["unmatched"], f"{x['on_cpu'] * 100:.1f} %",
            f"{x['runnable'] * 100:.1f} %"] for (r, c, hz), x in results])
    print("(its main thread's share of the window on a CPU, and runnable but waiting for a CPU: the machine's\n"
          " load; \"not matched\": contacts still under way when the window closed, or lost)")
    table(f"2. CPU of cellbridge ros2 (% of one core over {window:.0f} s; a press held, every topic read)",
          ["skin", "ros2 CPU", "daemon CPU", "state/s", "contacts/s", "markers/s", "diagnostics/s"],
          [[f"{r}x{c} at {hz:.0f} Hz", f"{x['cpu'] * 100:.1f} %", f"{x['daemon_cpu'] * 100:.1f} %",
            f"{x['rates']['tactile_state']:.0f}", f"{x['rates']['contacts']:.0f}", f"{x['rates']['markers']:.0f}",
            f"{x['rates']['diagnostics']:.1f}"] for (r, c, hz), x in results])
    late = [x["late"] for _, x in results]
    if any(late):
        print(f"(the feeder wrote {late} slots more than a period late: the machine was busy)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
