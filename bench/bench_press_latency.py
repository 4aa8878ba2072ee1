"""Press in the world → its contact on ZeroMQ: the latency a robot feels, real processes.

Run: ``.venv/bin/python bench/bench_press_latency.py [--presses 40] [--reporting periodic]``
(``--reporting event:40`` as ``cellbridge demo`` runs its skin; ``--side 4``; ``--rate 100``;
``--virtual``: the same in virtual time, see below).

Starts ``cellbridge mesh up`` (a side×side grid, one gateway) and ``cellbridge daemon`` on
its gateway's pty, as a robot runs them, and subscribes to the daemon's ``contact`` topic.
Once every element is calibrated it presses ``--presses`` times, one at a time, at random
points of the skin (0.3 s each, 3 N, 20 mm), through the world process, which answers with
the host monotonic second the press starts; a press's latency is from that second to the
first ``contact`` message holding a contact within one element's side (40 mm) of the press, received here (same
host, same monotonic clock). Prints p50/p99/max and presses never seen, then the daemon's
own account (health: late elements, unknown frames). Every process is stopped on exit.

``--virtual`` runs the skin in virtual time (``VirtualMesh`` with the real-time latency
model, the readout configured as the real-time shells configure it) and feeds its
gateway's bytes, at their virtual times, into the daemon offline (its pipeline and its
contact loop's schedule, the production contact path inline, estimating when the daemon
would): the same latency without the machine's load in it (deterministic by ``--seed``),
and split into its parts (first sample showing the press at the host; first contact).
Each press starts at a random point of the sampling period. ``--ideal`` leaves the
processes' latency out too (messages and wakes take no time): the floor that the gates,
the readout schedule and the cells' bit rate set, which no host can beat. The position
error counts only the axes the readings resolve (a press inside one element is reported
at its centre along the other, its σ spanning the element), and ``untrue`` reports are
those ``cellbridge demo --check`` calls so: off by more than 1 mm and 3 σ on an axis with
no unknown element listed.

``--tcp`` reads the gateway's TCP port (``mesh up --tcp``, a ``socket://`` link) instead of
its pty: the kernel hands a pty's bytes to their reader from a worker thread at normal
priority, which the real-time skin holds back at the tail (the trace's "the gateway began
writing -> the daemon read the record" row says how much); a socket's go in the writer's
own time. A robot's USB serial line takes the kernel's path of a pty, on a machine whose
real-time work is not 17 emulated processes.

``--trace`` (real processes) runs the daemon through ``bench/press_trace.py``, which notes
when each reading, look, estimate and publish happened, and prints per press what its
contact waited for (each step's p50/p90 over every press, then the median press and the
slowest tenth step by step); then every skin frame's way on the gateway's own plan of
gates: gate end → the gateway began writing its record (the record's age: the skin's
readout) → the daemon read it (the line) → given out, and how far the daemon's time of
the frame is from its gate start. Run the skin at real-time priority so other work does not
count: ``chrt -f 1 .venv/bin/python bench/bench_press_latency.py --reporting event:40
--presses 60 --trace``.

Run so (real-time priority P), the daemon, its contact worker and this subscriber run at
P + 2, above the emulated skin (the bridges at P, the medium at P + 1: it stands for the
wire, ``emulator/realtime/realtime.py``): on a robot the bridges are chips on the skin and take
no time of the host's CPU, while here 16 bridge processes, the medium and the world share
two cores with the daemon, and at one priority a FIFO scheduler lets any of them finish
its turn before the daemon runs. ``--same-priority`` keeps the daemon and the subscriber
at P (the skin's emulation then counts in the latency, as it did before this option).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgpack
import zmq
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml
from cellbridge.emulator.world.world import Contact

from daemon_harness import free_port
from realskin import world_press
from timing import fifo_every_thread, table
from unwind import unwind_on_signals

PRESS_S = 1.0
GAP_S = 0.5
#: A contact this close to a press is its contact: one element's side (a press inside one
#: element is reported at the element's centre along an axis it cannot resolve)
NEAR_M = 0.040


def _free_port() -> int:
    return free_port()


def _start(cmd: list[str], prefix: tuple[str, ...] = (), **kw: object) -> subprocess.Popen:
    """``cellbridge CMD`` in a session of its own (``prefix``: e.g. a ``chrt`` command)."""
    return subprocess.Popen([*prefix, sys.executable, "-m", "cellbridge", *cmd], start_new_session=True, **kw)  # type: ignore[call-overload]


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
        except ProcessLookupError:
            pass


def _host_priority(same: bool) -> tuple[str, ...]:
    """The command prefix that runs the daemon above the skin: two real-time priorities
    above this process's FIFO priority, which ``mesh up``'s bridges inherit (its medium
    runs one above them); none when this process is not real-time or ``same``."""
    if same or os.sched_getscheduler(0) != os.SCHED_FIFO:
        return ()
    top = os.sched_get_priority_max(os.SCHED_FIFO)
    return ("chrt", "-f", str(min(top, os.sched_getparam(0).sched_priority + 2)))


def run_virtual(args: argparse.Namespace, mesh) -> tuple[list[float], list[float], int, list[tuple[float, float, int, int]]]:
    """(press -> first sample showing it at the host, press -> first contact near it, missed)
    in virtual time; milliseconds."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.shell.offline import OfflineDaemon
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
    from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, READOUT_HOP, READOUT_WINDOW
    from cellbridge.emulator.realtime.realtime import reporting_arg
    from cellbridge.emulator.world.world import World

    rng = random.Random(args.seed)
    span = (args.side - 1) * mesh.side
    # routes formed, mesh time and calibration settled (n_baseline quiet readings: event-based
    # bridges send an idle element's reading once a heartbeat, 1 s)
    first = len(mesh.bridges) * 0.1 + (20.0 if args.reporting == "periodic" else 60.0)
    presses = []
    for i in range(args.presses):
        x, y = args.at if args.at else (rng.uniform(0, span), rng.uniform(0, span))
        # a press starts anywhere within the sampling period (a part-way sample, or none)
        start = first + i * (args.hold + GAP_S) + rng.uniform(0, 1.0 / args.rate)
        presses.append(Contact(start, args.hold, x, y, 3.0, 0.02))
    # the firmware as the real-time shells configure it (emulator/realtime/process_bridge.py)
    vm = VirtualMesh(mesh, seed=args.seed, world=World(mesh, presses), latency=None if args.ideal else Latency(),
                     ack_slack=ACK_SLACK, random_epochs=True, readout_acks=False, readout_window=READOUT_WINDOW,
                     readout_hop=READOUT_HOP, settings=Settings(rate_hz=args.rate, reporting=reporting_arg(args.reporting)))
    vm.run(presses[-1].start + args.hold + 1.0)
    reads = [(t / CLOCK_HZ, "gw", data) for t, data in vm.serial_chunks[mesh.gateways[0]]]
    contact = dict(_setting(kv) for kv in args.contact)
    # The daemon offline: the service's schedule (cellbridge.daemon.core.contact_schedule) in
    # virtual time: a look when data came, when a frame's deadline passes or at the tick,
    # no sooner than the pacer allows after the last look.
    d = OfflineDaemon(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "contact": contact}),
                      topics={"element", "contact"})
    sample_at: dict[int, float] = {}
    contact_at: dict[int, float] = {}
    seen: dict[int, list[dict]] = {k: [] for k in range(len(presses))}  # contacts during each press

    def near(now: float, x: float, y: float) -> list[int]:
        return [k for k, c in enumerate(presses) if c.start <= now < c.start + c.duration + 0.5
                and (c.x - x) ** 2 + (c.y - y) ** 2 <= NEAR_M ** 2]

    for now, topic, m in d.run(reads, start=0.0):
        if topic == "element":  # (published at the read's time)
            for touched in m["touched"]:
                if touched:
                    for k, c in enumerate(presses):
                        if c.start <= now < c.start + PRESS_S and k not in sample_at:
                            sample_at[k] = now - c.start
        elif topic == "contact":
            if args.verbose and any(c.start - 0.05 <= now < c.start + 0.8 for c in presses):
                lag = now - m["t_sample"] if m["t_sample"] is not None else math.nan
                print(f"  {now:.3f} frame lag {1000 * lag:.0f} ms, unknown {len(m['unknown'])}")
            for c in m["contacts"]:
                for k in near(now, c["x"], c["y"]):
                    contact_at.setdefault(k, now - presses[k].start)
                for k, pr in enumerate(presses):
                    if pr.start <= now < pr.start + pr.duration and c.get("missed", 0) == 0:
                        seen[k].append(c)
    lat_s = [1000 * v for v in sample_at.values()]
    lat_c = [1000 * v for v in contact_at.values()]
    return lat_s, lat_c, len(presses) - len(contact_at), [_truth(presses[k], cs) for k, cs in seen.items()]


def _truth(press: Contact, contacts: list[dict]) -> tuple[float, float, int, int]:
    """What ``cellbridge demo --check`` judges: the median position (mm, on the axes the
    readings resolve) and force (%) errors of the steady half of the press's longest-lived
    id, how many ids it got, and how many of its reports were untrue (off by more than
    1 mm and 3 σ on an axis, with no unknown element listed)."""
    if not contacts:
        return math.nan, math.nan, 0, 0
    ids = [c["id"] for c in contacts]
    main = max(set(ids), key=ids.count)
    mine = [c for c in contacts if c["id"] == main]
    steady = mine[len(mine) // 2:]
    x, y, f = (sorted(c[k] for c in steady)[len(steady) // 2] for k in ("x", "y", "force"))
    ox, oy = steady[-1].get("observable") or (True, True)
    err = math.hypot((x - press.x) if ox else 0.0, (y - press.y) if oy else 0.0)
    untrue = sum(1 for c in contacts if not c.get("unknown_near") and any(
        abs(c[a] - t) > max(1e-3, 3 * c.get("sigma_" + a, 0.0)) for a, t in (("x", press.x), ("y", press.y))))
    return 1e3 * err, 100 * abs(f - press.force) / press.force, len(set(ids)), untrue


def _skin_share(log: Path, frames: list, records: list, mesh, rate: int, since: float) -> None:
    """Every skin frame the daemon took from ``since`` (the first press) on, from its gate
    end on the gateway's own plan (its last line names the ticks of two gates 10 s apart;
    mesh time between is a straight line) to the daemon giving it out, apart from the
    daemon's own map of mesh time; and split at the gateway by its record's age (when it
    began writing the record): the skin's readout, then the line and the daemon's read."""
    from cellbridge.emulator.firmware.commands import Settings

    gw = mesh.gateways[0]
    plan = None
    for line in log.read_text().splitlines():
        if line.startswith("{"):
            try:
                d = json.loads(line)
            except ValueError:
                continue
            if d.get("bridge") == gw:
                plan = d.get("gates")
    if not plan or len(plan) != 2 or not frames:
        print("\n(no gate plan in the gateway's last line: no gate-end breakdown)")
        return
    (k0, t0), (k1, t1) = sorted((int(k), v / 50e6) for k, v in plan.items())
    gates = Settings(rate_hz=rate).measure_cycles() / 50e6
    def planned(g: int) -> float:  # host second the frame at global cycle g started its gates, on the plan
        return t0 + (g * rate / 50e6 - k0) * (t1 - t0) / (k1 - k0)

    taken = [(now, t, g) for now, t, g, *_ in frames if now >= since]
    if not taken:
        return
    rows = []
    for what, d in (("gate end (the gateway's plan) -> given out by the daemon",
                     sorted(1000 * (now - (planned(g) + gates)) for now, _t, g in taken)),
                    ("the frame's host time the daemon stamps - its gate start on the plan",
                     sorted(1000 * (t - planned(g)) for _now, t, g in taken))):
        q = [d[min(len(d) - 1, int(x * len(d)))] for x in (0.5, 0.9, 0.99)]
        rows.append([what, len(d), *(f"{x:.1f}" for x in q), f"{d[-1]:.1f}"])
    aged = [(now, k * 50_000_000 // r, age) for now, k, r, age in records if now >= since and age and r == rate]
    for what, d in (("gate end -> the gateway began writing its record (the record's age)",
                     sorted(1000 * (age * 1e-6 - gates) for _now, _g, age in aged)),
                    ("the gateway began writing -> the daemon read the record",
                     sorted(1000 * (now - planned(g) - age * 1e-6) for now, g, age in aged))):
        if d:
            q = [d[min(len(d) - 1, int(x * len(d)))] for x in (0.5, 0.9, 0.99)]
            rows.append([what, len(d), *(f"{x:.1f}" for x in q), f"{d[-1]:.1f}"])
    table("every skin frame during the presses", ["what", "frames", "p50 ms", "p90 ms", "p99 ms", "max ms"], rows)


def _setting(text: str) -> tuple[str, int | float]:
    """``KEY=VALUE`` of ``--contact``: an integer stays one (birth_frames), anything else is a float."""
    key, _, value = text.partition("=")
    try:
        return key, int(value)
    except ValueError:
        return key, float(value)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=4)
    ap.add_argument("--gateway", type=int, default=None,
                    help="the gateway's bridge id (default: the grid generator's, see cellbridge mesh gen)")
    ap.add_argument("--rate", type=int, default=100)
    ap.add_argument("--reporting", default="periodic", help="periodic or event:THRESHOLD (default periodic)")
    ap.add_argument("--presses", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--contact", action="append", default=[], metavar="KEY=VALUE",
                    help="a [contact] setting for the daemon (e.g. rate=250); repeatable")
    ap.add_argument("--verbose", action="store_true", help="print every contact message seen")
    ap.add_argument("--hold", type=float, default=PRESS_S, help=f"seconds each press lasts (default {PRESS_S})")
    ap.add_argument("--at", type=float, nargs=2, metavar=("X", "Y"), default=None,
                    help="press here every time instead of at random points (m)")
    ap.add_argument("--virtual", action="store_true", help="virtual time (deterministic; no machine load in it)")
    ap.add_argument("--ideal", action="store_true",
                    help="with --virtual: no process latency either (the floor the gates, the schedule and the "
                         "cells set)")
    ap.add_argument("--same-priority", action="store_true",
                    help="under chrt, run the daemon and this subscriber at the skin's real-time priority, "
                         "not above it (see the module)")
    ap.add_argument("--tcp", action="store_true",
                    help="read the gateway's TCP port (mesh up --tcp, a socket:// link) instead of its pty "
                         "(see the module's text)")
    ap.add_argument("--trace", action="store_true",
                    help="run the daemon with a timing trace (bench/press_trace.py) and print, for the median "
                         "and the slowest tenth of presses, what their contact waited for")
    args = ap.parse_args()
    unwind_on_signals()
    mesh = meshgen.grid(args.side, args.side, None if args.gateway is None else (args.gateway,))
    n = len(mesh.bridges)
    if args.virtual:
        lat_s, lat_c, missed, truth = run_virtual(args, mesh)
        rows = []
        pos = [t[0] for t in truth if math.isfinite(t[0])]
        force = [t[1] for t in truth if math.isfinite(t[1])]
        for name, xs in (("first touched sample at the host", lat_s), ("first contact near the press", lat_c),
                         ("position error mm (steady half)", pos), ("force error % (steady half)", force)):
            xs.sort()
            rows.append([name, len(xs)] + [f"{xs[min(len(xs) - 1, int(q * len(xs)))]:.1f}" if xs else "nan"
                                           for q in (0.5, 0.9, 0.99)] + [f"{xs[-1]:.1f}" if xs else "nan"])
        model = "no process latency: the floor" if args.ideal else "real-time latency model"
        table(f"{mesh.name}, {args.rate} Hz, {args.reporting}, virtual time ({model}): "
              f"press in the world ->", ["what", "presses", "p50 ms", "p90 ms", "p99 ms", "max ms"], rows)
        bad = [k for k, t in enumerate(truth) if not (t[0] <= 1.0 and t[1] <= 5.0 and t[2] == 1)]
        print(f"\nmissed presses: {missed}; presses not within 1 mm (resolved axes) and 5 % with one id: "
              f"{len(bad)} {[(k, *truth[k]) for k in bad[:5]]}; untrue reports: {sum(t[3] for t in truth)}")
        return
    work = Path(tempfile.mkdtemp(prefix="bench-press-"))
    (work / "skin.toml").write_text(mesh_to_toml(mesh))
    base = free_port(3)
    pub, ctl = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    rt = os.sched_getscheduler(0) == os.SCHED_FIFO
    prio = (f"skin at real-time priority {os.sched_getparam(0).sched_priority}, daemon and subscriber "
            + ("at the same" if args.same_priority else "two above (the medium one above)") if rt else "no real-time priority")
    print(f"{mesh.name}: {n} bridges at {args.rate} Hz ({args.reporting}), {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}; {prio}")
    procs: list[subprocess.Popen] = []
    ctx: zmq.Context = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    for t in (b"contact", b"health"):
        sub.setsockopt(zmq.SUBSCRIBE, t)
    sub.connect(pub)
    try:
        up = _start(["mesh", "up", str(work / "skin.toml"), "--base-port", str(base), "--rate", str(args.rate),
                     "--reporting", args.reporting, *(["--tcp"] if args.tcp else [])], stdout=subprocess.PIPE, stderr=open(work / "mesh.log", "w"),
                    text=True)
        procs.append(up)
        device = ""
        deadline = time.monotonic() + 60
        while not device and time.monotonic() < deadline:
            assert up.stdout is not None  # stdout=PIPE
            line = up.stdout.readline()
            if not line:
                raise RuntimeError(f"mesh up ended: {(work / 'mesh.log').read_text()[-500:]}")
            device = next((w for w in line.split() if w.startswith("socket://" if args.tcp else "/dev/")), "")
        (work / "daemon.toml").write_text(
            f'[pub]\nendpoint = "{pub}"\n\n[control]\nendpoint = "{ctl}"\n\n[daemon]\nlog_format = "text"\n\n'
            f'[[link]]\nname = "gateway"\nurl = "{device}"\n'
            + ("\n[contact]\n" + "".join(f"{kv}\n" for kv in args.contact) if args.contact else ""))
        host = _host_priority(args.same_priority)  # the daemon's (and then this subscriber's) chrt prefix
        if args.trace:
            daemon = subprocess.Popen([*host, sys.executable, str(Path(__file__).with_name("press_trace.py")), "--config",
                                       str(work / "daemon.toml"), "--trace", str(work / "trace.msgpack")],
                                      start_new_session=True, stderr=open(work / "daemon.log", "w"))
        else:
            daemon = _start(["daemon", "--config", str(work / "daemon.toml")], host,
                            stderr=open(work / "daemon.log", "w"))
        procs.append(daemon)
        if host:
            fifo_every_thread(int(host[2]))  # ZeroMQ's I/O thread too: it was started above
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            if sub.poll(1000):
                topic, body = sub.recv_multipart()
                if topic == b"health" and msgpack.unpackb(body).get("layout", {}).get("calibration", {}).get("ready", 0) >= n:
                    break
        else:
            raise RuntimeError("the daemon did not calibrate every element in 180 s")
        rng = random.Random(args.seed)
        span = (args.side - 1) * mesh.side
        lat: list[float] = []
        pressed: list[tuple[float, float, float, float | None]] = []  # (start, x, y, latency ms)
        missed = 0
        health: dict = {}
        for _ in range(args.presses):
            x, y = args.at if args.at else (rng.uniform(0, span), rng.uniform(0, span))
            start = world_press(base, x, y, args.hold)
            seen = None
            end = start + args.hold + 1.0
            while time.monotonic() < end:
                if not sub.poll(50):
                    continue
                topic, body = sub.recv_multipart()
                got = time.monotonic()
                msg = msgpack.unpackb(body)
                if topic == b"health":
                    health = msg
                elif args.verbose and msg.get("contacts"):
                    print(f"  {got - start:+.3f} s {[(c['id'], round(c['x'], 4), round(c['y'], 4), round(c['force'], 3), c['missed']) for c in msg['contacts']]} "
                          f"unknown {msg.get('unknown')} "
                          f"pressed ({x:.4f}, {y:.4f})")
                if topic == b"contact" and seen is None and got >= start and any(
                        (c["x"] - x) ** 2 + (c["y"] - y) ** 2 <= NEAR_M ** 2 for c in msg.get("contacts", [])):
                    seen = got - start
            pressed.append((start, x, y, None if seen is None else 1000 * seen))
            if seen is None:
                missed += 1
            else:
                lat.append(1000 * seen)
            time.sleep(GAP_S)
        lat.sort()

        def pct(q: float) -> str:
            return f"{lat[min(len(lat) - 1, int(q * len(lat)))]:.1f}" if lat else "nan"

        table("press in the world -> first contact near it on ZeroMQ",
              ["presses", "seen", "p50 ms", "p90 ms", "p99 ms", "max ms", "load"],
              [[args.presses, len(lat), pct(0.5), pct(0.9), pct(0.99), f"{lat[-1]:.1f}" if lat else "nan",
                f"{os.getloadavg()[0]:.1f}"]])
        late = health.get("late_estimates", health.get("moments", {}).get("late_estimates", "?"))
        print(f"\nmissed presses: {missed}; health late estimates: {late}")
        if args.trace:
            _stop(daemon)
            with open(work / "trace.msgpack", "rb") as f:
                trace = msgpack.unpack(f, strict_map_key=False)
            from press_trace import breakdown, print_breakdown

            print_breakdown(breakdown(trace, pressed, 1.0 / args.rate, args.hold))
            _stop(up)  # its bridges' last lines name the gateway's plan of gates
            _skin_share(work / "mesh.log", trace.get("k", []), trace.get("r", []), mesh, args.rate,
                        pressed[0][0] if pressed else 0.0)
            (work / "presses.json").write_text(json.dumps(pressed))
            print(f"\ntrace and presses kept in {work}")
    finally:
        sub.close()
        for p in reversed(procs):
            _stop(p)


if __name__ == "__main__":
    main()
