"""Recording figures: recorder CPU and MB per hour, replay timing and speed, proxy latency.

Run: ``.venv/bin/python bench/bench_recording.py [--quick]``.

1. **Recorder cost** for a 16×16 skin at 100 Hz: the real daemon replays, at recorded
   speed, a capture of 256 bridges sampling at 100 Hz (a press in the middle), and
   ``cellbridge record`` records it: default topics (contact, element, health, topology),
   then also ``raw``, then also ``serial``. CPU is the recorder's own (user + system, from
   ``wait4``) over the capture's duration; MB per hour is the file size scaled to an hour.
2. **Round trip timing**: a live emulated 4×4 skin in real processes and its daemon,
   recorded through a press, then ``cellbridge replay --rate 1`` onto ZeroMQ: for every
   pair of consecutive messages, |interval at the replay's subscriber − interval as
   recorded|, and whether every payload came back equal, in order; then where the time
   goes: the same against a live subscriber of the daemon, the recorder's stamps against
   that subscriber, and how late the replay sent (its own report).
3. **Replay as fast as possible**: the 16×16 recording with ``raw`` through
   ``cellbridge replay --fast`` to a subscriber that counts (messages/s).
4. **Proxy added latency**: a PUB sending 2 000 stamped messages at 1 kHz to a SUB,
   directly and through ``cellbridge proxy``; the difference of the latency quantiles.

The machine is shared: timing figures are sensitive to other load.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal
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
from cellbridge.daemon.shell.capture import write_capture

from cellbridge.recording import codec
from cellbridge.recording.mcapfile import read_messages
from daemon_harness import daemon, free_port, write_config
from daemon_traffic import GridFrames
from live_skin import Collector, calibrated, cellbridge_cmd, group, live_skin
from recording_helpers import same_payload
from timing import table


def make_capture(path: Path, seconds: float, rows: int = 16, cols: int = 16, rate: float = 100.0) -> None:
    sk = GridFrames(rows=rows, cols=cols, rate=rate)
    t0 = 1_750_000_000.0
    records = [(t0, sk.hellos() + sk.beacons())]
    n = int(seconds * rate)
    press = (0.30, 0.30, 3.0, 0.02)
    for k in range(n):
        on = n // 3 <= k < 2 * n // 3
        records.append((t0 + 0.01 + k / rate, sk.slot(k, press if on else None)))
    write_capture(path, records)


def recorder_cost(tmp: Path, capture: Path, seconds: float, extra: list[str], name: str) -> tuple[float, float, int]:
    """(CPU %, MB per hour, messages) of `cellbridge record` on a daemon replaying the capture."""
    cfg = tmp / f"{name}.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": f"replay:{capture}", "replay_speed": 1.0,
                                    "wait_for_subscriber": True, "exit_when_done": True}],
                             health={"interval": 1.0})
    out = tmp / f"{name}.mcap"
    rec = subprocess.Popen(cellbridge_cmd("record", str(out), "--endpoint", endpoints["pub"], *extra),
                           stderr=subprocess.PIPE, start_new_session=True)
    try:
        with daemon(cfg, tmp / f"{name}-daemon.log") as proc:
            proc.wait(seconds + 120)
        time.sleep(0.5)
        os.killpg(rec.pid, signal.SIGINT)
        _, status, usage = os.wait4(rec.pid, 0)
        rec.returncode = os.waitstatus_to_exitcode(status)
    finally:
        if rec.returncode is None:
            os.killpg(rec.pid, signal.SIGKILL)
            rec.wait()
    stats = json.loads(rec.stderr.read().decode().strip().splitlines()[-1])  # type: ignore[union-attr]
    cpu = (usage.ru_utime + usage.ru_stime) / seconds
    mb_h = out.stat().st_size / 1e6 / seconds * 3600
    return 100 * cpu, mb_h, stats["messages"]


def round_trip(tmp: Path, press_s: float) -> dict[str, Any]:
    """Record a live 4x4 skin through a press, replay it at --rate 1, and compare intervals.

    Three subscribers' clocks: a live one beside the recorder (receiving in a thread of its
    own, so this script's waits do not delay its stamps), the recorder's stamps in the file
    (publish time), and the replay's subscriber. For each pair of consecutive messages:
    |interval replayed - interval recorded| (what replay adds), |interval replayed -
    interval live| (the whole round trip against what a subscriber of the daemon saw), and
    |interval recorded - interval live| (what recording adds, with the two subscribers'
    own wake-up jitter). The replay also reports how late it sent each message."""
    work = tmp / "live"
    out = work / "skin.mcap"
    with live_skin(work) as skin:
        live = Collector(skin.pub, (b"",))
        try:
            with group(cellbridge_cmd("record", str(out), "--endpoint", skin.pub, "--topics", "all"),
                       stderr=open(work / "record.log", "wb")) as rec, live.in_background():
                time.sleep(0.3)
                with skin.daemon(skin.daemon_config(source="bench")):
                    if not live.wait(calibrated(skin.elements), 120):
                        raise RuntimeError("the daemon did not calibrate within 120 s")
                    skin.press(0.057, 0.040, duration=press_s)
                    live.wait(lambda t, m: t == "contact" and bool(m["contacts"]), 60)
                    time.sleep(press_s)
                    os.killpg(rec.pid, signal.SIGTERM)
                    rec.wait(15)
        finally:
            live.close()
    recorded = [(m.topic, m.publish_ns * 1e-9, codec.decode(m.topic, m.data)) for m in read_messages(out)]
    endpoint = f"tcp://127.0.0.1:{free_port()}"
    sub = Collector(endpoint)
    try:
        with group(cellbridge_cmd("replay", str(out), "--endpoint", endpoint, "--rate", "1", "--wait-subscriber"),
                   stderr=subprocess.PIPE) as proc:
            while len(sub.messages) < len(recorded) and proc.poll() is None:
                sub.pump(0.5)
            sub.pump(0.5)
            proc.wait(30)
            report = json.loads(proc.stderr.read().decode().strip().splitlines()[-1])  # type: ignore[union-attr]
    finally:
        sub.close()
    got = sub.payloads()
    same = len(got) == len(recorded) and all(a[0] == b[0] and same_payload(a[1], b[2])
                                             for a, b in zip(got, recorded))
    rec_t = np.array([t for _, t, _ in recorded])
    rep_t = np.array([t for _, _, t in sub.messages[:len(recorded)]])
    err = np.abs(np.diff(rep_t) - np.diff(rec_t[:len(rep_t)])) * 1e3
    at = {(t, m["seq"]): rt for (t, _, rt), (_, m) in zip(live.messages, live.payloads())}
    triples = [(pt, at[(t, m["seq"])], rt) for (t, pt, m), rt in zip(recorded, rep_t) if (t, m["seq"]) in at]
    rec_live = np.abs(np.diff([a for a, _, _ in triples]) - np.diff([b for _, b, _ in triples])) * 1e3
    rep_live = np.abs(np.diff([c for _, _, c in triples]) - np.diff([b for _, b, _ in triples])) * 1e3
    q = (lambda x, p: float(np.percentile(x, p)) if len(x) else float("nan"))
    return {"messages": len(recorded), "same": same, "p50": q(err, 50), "p99": q(err, 99),
            "max": float(err.max()) if len(err) else float("nan"),
            "seconds": float(rec_t[-1] - rec_t[0]), "floor_p99": q(rec_live, 99), "floor_p50": q(rec_live, 50),
            "live_p50": q(rep_live, 50), "live_p99": q(rep_live, 99), "matched": len(triples),
            "late": report.get("late_ms", {})}


def replay_fast(tmp: Path, recording: Path) -> tuple[int, float, int]:
    endpoint = f"tcp://127.0.0.1:{free_port()}"
    n = sum(1 for _ in read_messages(recording))
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.rcvhwm = 0
    sub.subscribe(b"")
    sub.connect(endpoint)
    got = 0
    with group(cellbridge_cmd("replay", str(recording), "--endpoint", endpoint, "--fast", "--wait-subscriber"),
               stderr=subprocess.PIPE) as proc:
        while got < n and sub.poll(5000):
            sub.recv_multipart()
            got += 1
        proc.wait(60)
        report = json.loads(proc.stderr.read().decode().strip().splitlines()[-1])  # type: ignore[union-attr]
    sub.close(0)
    ctx.term()
    return n, report["sent"] / report["seconds"], got


def _latency(pub_endpoint: str, sub_endpoint: str, n: int, rate: float = 1000.0) -> np.ndarray:
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.bind(pub_endpoint)
    sub = ctx.socket(zmq.SUB)
    sub.subscribe(b"x")
    sub.rcvhwm = 0
    sub.connect(sub_endpoint)
    lat: list[float] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            if sub.poll(100):
                _, body = sub.recv_multipart()
                lat.append(time.perf_counter() - msgpack.unpackb(body)["t"])

    for _ in range(200):  # until the path is joined
        pub.send_multipart([b"x", msgpack.packb({"t": time.perf_counter()})])
        if sub.poll(10):
            break
    while sub.poll(100):
        sub.recv_multipart()
    th = threading.Thread(target=receive)
    th.start()
    t_next = time.perf_counter()
    for _ in range(n):
        t_next += 1.0 / rate
        while time.perf_counter() < t_next:
            time.sleep(max(0.0, t_next - time.perf_counter() - 0.0002))
        pub.send_multipart([b"x", msgpack.packb({"t": time.perf_counter(), "pad": b"\0" * 200})])
    time.sleep(0.5)
    done.set()
    th.join()
    pub.close(0)
    sub.close(0)
    ctx.term()
    return np.array(lat) * 1e3


def proxy_latency(n: int) -> tuple[np.ndarray, np.ndarray]:
    port = free_port()
    direct = _latency(f"tcp://127.0.0.1:{port}", f"tcp://127.0.0.1:{port}", n)
    back, front = free_port(), free_port()
    with group(cellbridge_cmd("proxy", "--front", f"tcp://127.0.0.1:{front}", "--back",
                              f"tcp://127.0.0.1:{back}"), stderr=subprocess.DEVNULL):
        time.sleep(1.0)
        via = _latency(f"tcp://127.0.0.1:{back}", f"tcp://127.0.0.1:{front}", n)
    return direct, via


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs (figures less steady)")
    ap.add_argument("--only", choices=("recorder", "roundtrip", "proxy"), help="one part only (recorder: and replay)")
    args = ap.parse_args()
    part = (lambda name: args.only in (None, name))
    seconds = 10.0 if args.quick else 30.0
    with tempfile.TemporaryDirectory(prefix="bench-recording-") as d:
        tmp = Path(d)
        if part("recorder"):
            capture = tmp / "skin16.cbcap"
            make_capture(capture, seconds)
            rows = []
            for name, extra in (("default topics", []), ("+ raw", ["--raw"]),
                                ("+ raw + serial", ["--raw", "--serial"])):
                cpu, mb_h, msgs = recorder_cost(tmp, capture, seconds, extra, name.replace(" ", "").replace("+", "_"))
                rows.append([name, f"{cpu:.1f}", f"{mb_h:.0f}", msgs])
            table(f"Recorder, 16x16 skin at 100 Hz ({seconds:.0f} s through the daemon, zstd chunks)",
                  ["topics", "CPU %", "MB/hour", "messages"], rows)
            n, rate, got = replay_fast(tmp, tmp / "_raw.mcap")
            table("Replay as fast as possible (the 16x16 recording with raw)",
                  ["messages", "messages/s", "received"], [[n, f"{rate:.0f}", got]])
        if part("roundtrip"):
            gc.disable()  # the subscribers here are the instrument: no collection pauses in their stamps
            try:
                rt = round_trip(tmp, 2.0)
            finally:
                gc.enable()
            print(f"load average now: {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)")
            table("Round trip: live 4x4 skin recorded through a press, replayed at --rate 1",
                  ["messages", "recorded s", "same payloads, order", "|Δinterval| p50 ms", "p99 ms", "max ms"],
                  [[rt["messages"], f"{rt['seconds']:.1f}", rt["same"], f"{rt['p50']:.3f}", f"{rt['p99']:.3f}",
                    f"{rt['max']:.2f}"]])
            late = rt["late"]
            table(f"Round trip, where the time goes (|Δinterval| between two clocks, {rt['matched']} messages)",
                  ["clocks compared", "p50 ms", "p99 ms"],
                  [["replay's subscriber vs recorded publish times (replay)", f"{rt['p50']:.3f}", f"{rt['p99']:.3f}"],
                   ["replay's subscriber vs a live subscriber (whole round trip)", f"{rt['live_p50']:.3f}",
                    f"{rt['live_p99']:.3f}"],
                   ["recorded publish times vs a live subscriber (recording + 2 subscribers' jitter)",
                    f"{rt['floor_p50']:.3f}", f"{rt['floor_p99']:.3f}"],
                   ["replay's sends after their due time (its own report)", f"{late.get('p50', float('nan')):.3f}",
                    f"{late.get('p99', float('nan')):.3f}"]])
        if not part("proxy"):
            return 0
        direct, via = proxy_latency(1000 if args.quick else 2000)
        q = [50, 99]
        dq, vq = np.percentile(direct, q), np.percentile(via, q)
        table("Proxy: PUB -> SUB at 1 kHz, direct and through cellbridge proxy (ms)",
              ["path", "p50", "p99", "messages"],
              [["direct", f"{dq[0]:.3f}", f"{dq[1]:.3f}", direct.size],
               ["via proxy", f"{vq[0]:.3f}", f"{vq[1]:.3f}", via.size],
               ["added", f"{vq[0] - dq[0]:.3f}", f"{vq[1] - dq[1]:.3f}", ""]])
    return 0


if __name__ == "__main__":
    sys.exit(main())
