"""Where the real-time skin's CPU goes: the firmware's own work against the cost of
running it as one process per bridge.

Run: ``.venv/bin/python bench/bench_skin_cpu_split.py [--seconds 10]`` (about 45 s).

``cellbridge mesh up`` of a periodic 4x4 at 100 Hz (``bench/bench_skin_rt.py``) spends
its CPU in 16 bridge processes and the medium. This script measures, on this machine:

1. **the work itself**: the same skin in the virtual-time mesh (one process, the same
   firmware, chip model and medium model, the readout configured as the real-time shells
   configure it), its CPU (``process_time``) per second of skin time: what the skin costs
   when every call runs back to back with warm caches; once with each count computed when
   its sample is taken, once with the chip computing the next samples' counts together
   after a wake that took one, as the bridge processes do (``PREFETCH``);
2. **a wake**: the CPU of one process waking from ``poll`` with a timeout, doing nothing
   (the floor of every bridge timer and medium delivery), and of one UDP datagram sent on
   loopback to a process that wakes for it and reads it (both processes' CPU: the floor
   of every message between a bridge and the medium);
3. what these floors make of the wakes and messages a real-time 4x4 counts
   (``--wakes`` and ``--messages`` per second, from ``bench_skin_rt.py``'s wake table and
   the medium's counters: defaults are a periodic 4x4 at 100 Hz);
4. the same skin as (1) in one process paced to the host's clock (sleeping until each
   next event): what the skin would cost in real time with every bridge and the medium in
   one process, about the floor of any layout of its processes.

The difference between the real-time skin's CPU and (1) + (3) is what the interpreter
loses running each wake's code with cold caches, among 17 processes on few cores.
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import time

import numpy as np
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, PREFETCH, READOUT_HOP, READOUT_WINDOW
from cellbridge.emulator.realtime.realtime import CLOCK_HZ

from timing import table


def skin_work(seconds: float, prefetch: int = 0) -> float:
    """CPU (% of one core) of a periodic 4x4 at 100 Hz in virtual time, after 5 s of start-up;
    ``prefetch``: the chip computes that many samples' counts ahead after a wake that took
    one, as the bridge processes do (``PREFETCH``; the same skin, its counts computed together)."""
    vm = VirtualMesh(meshgen.grid(4, 4), seed=1, readout=True, readout_acks=False, readout_window=READOUT_WINDOW,
                     readout_hop=READOUT_HOP, ack_slack=ACK_SLACK, prefetch=prefetch)
    vm.run(5.0)
    t0 = time.process_time()
    vm.run(seconds)
    return 100.0 * (time.process_time() - t0) / seconds


def paced_skin(seconds: float) -> tuple[float, float, float]:
    """The same skin in one process paced to the host's clock: it sleeps until its next
    event's instant and then runs everything due (a late wake runs more at once). What
    the skin costs in real time with no process per bridge and no datagrams: about the
    floor of any layout of its processes. (CPU in % of one core, sleeps a second, p99 of how
    late an event ran, ms.)"""
    vm = VirtualMesh(meshgen.grid(4, 4), seed=1, readout=True, readout_acks=False, readout_window=READOUT_WINDOW,
                     readout_hop=READOUT_HOP, ack_slack=ACK_SLACK)
    vm.run(5.0)
    w0, v0 = time.monotonic(), vm.tick
    c0, sleeps, late = time.process_time(), 0, []
    while (elapsed := time.monotonic() - w0) < seconds:
        nxt = vm.next_event()
        due = elapsed + 0.01 if nxt is None else (nxt - v0) / CLOCK_HZ
        if due > elapsed:
            time.sleep(due - elapsed)
            sleeps += 1
        now = time.monotonic() - w0
        late.append(now - due)
        vm.advance_to(v0 + int(now * CLOCK_HZ))
    cpu = time.process_time() - c0
    return 100.0 * cpu / seconds, sleeps / seconds, 1000.0 * float(np.percentile(late, 99))


def idle_wake(seconds: float) -> float:
    """CPU (µs) of one wake from poll(1 ms) with nothing to do."""
    p = select.poll()
    t0, w0, n = time.process_time(), time.monotonic(), 0
    while time.monotonic() - w0 < seconds:
        p.poll(1)
        n += 1
    return 1e6 * (time.process_time() - t0) / n


def datagram(seconds: float) -> float:
    """CPU (µs, sender and receiver together) of one UDP datagram on loopback that wakes
    its receiver: a child process echoes each one; half a round trip."""
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", 0))
    b.bind(("127.0.0.1", 0))
    a.connect(b.getsockname())
    b.connect(a.getsockname())
    pid = os.fork()
    if pid == 0:  # the echo: until the parent closes its end with an empty datagram
        try:
            a.close()
            while True:
                msg = b.recv(2048)
                if not msg:
                    break
                b.send(msg)
        finally:
            os._exit(0)
    b.close()
    try:
        t0, w0, n = os.times(), time.monotonic(), 0
        while time.monotonic() - w0 < seconds:
            a.send(b"x" * 100)
            a.recv(2048)
            n += 1
            time.sleep(0.001)  # both sides sleep between messages, as the skin's processes do
        a.send(b"")
        os.waitpid(pid, 0)
        t1 = os.times()
    finally:
        a.close()
    cpu = (t1.user - t0.user) + (t1.system - t0.system) + (t1.children_user - t0.children_user) \
        + (t1.children_system - t0.children_system)
    # the parent's sleep wake is counted in: subtract one idle wake per round trip
    return (1e6 * cpu / n - idle_wake(1.0)) / 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="skin time and measuring time per row (default 10)")
    ap.add_argument("--wakes", type=float, default=4900.0,
                    help="wakes/s of the real-time skin, bridges and medium (default 4900: 4x4 at 100 Hz)")
    ap.add_argument("--messages", type=float, default=3400.0,
                    help="datagrams/s between the bridges and the medium (default 3400: 4x4 at 100 Hz)")
    args = ap.parse_args()
    work = skin_work(args.seconds)
    work_ahead = skin_work(args.seconds, PREFETCH)
    paced, sleeps, late = paced_skin(args.seconds)
    wake = idle_wake(args.seconds / 2)
    msg = datagram(args.seconds / 2)
    floor = (args.wakes * wake + args.messages * msg) / 1e4
    table("where a periodic 4x4 at 100 Hz spends its CPU (this machine, now)",
          ["what", "µs each", "per second", "% of one core"],
          [["the skin's work, one process (virtual time)", "", "", f"{work:.1f}"],
           [f"the same, counts computed {PREFETCH} samples ahead as the bridge processes do", "", "",
            f"{work_ahead:.1f}"],
           ["a wake from poll, nothing to do", f"{wake:.0f}", f"{args.wakes:.0f}", f"{args.wakes * wake / 1e4:.1f}"],
           ["a datagram that wakes its reader (both sides)", f"{msg:.0f}", f"{args.messages:.0f}",
            f"{args.messages * msg / 1e4:.1f}"],
           ["work + wakes + datagrams", "", "", f"{work + floor:.1f}"],
           [f"the skin in one process paced to the clock (events p99 {late:.1f} ms late)", "", f"{sleeps:.0f}",
            f"{paced:.1f}"]])


if __name__ == "__main__":
    main()
