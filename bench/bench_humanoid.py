"""A humanoid's skin in one daemon: generation, the daemon at real speed, the estimate call.

Prints tables; asserts nothing. Run (several minutes; ``--quick``: 40 s recordings;
``--estimate-only``: section 3 alone, about a minute):

    .venv/bin/python bench/bench_humanoid.py [--seconds 120] [--quick] [--skip-daemon] [--estimate-only]

The skin is ``cellbridge/skins/humanoid.toml`` (1 144 elements of 40 mm on 12 patches of
11 links, 22 gateways), sampled at 100 Hz.

1. **Generation.** The skin's traffic over the recording, with presses: from 2 s on,
   rounds of 10 simultaneous presses, each on another patch (D 12-25 mm, F 2-8 N), held
   2 s, then 1 s untouched. Written by the frame-level generator
   (:class:`cellbridge.emulator.mesh.skin_traffic.SkinTraffic`: the gateways' READOUT records
   without the cells; its docstring says exactly what differs from the cycle-level mesh)
   into one capture file per gateway; its CPU per virtual second is quoted, beside the
   cycle-level virtual-time mesh's on a short stretch of the same skin.
2. **The daemon at real speed.** The real daemon process (its contact worker process
   included) with one ``replay:`` link per gateway at recorded speed, the humanoid as its
   layout, and a subscriber of ``contact`` and ``health``: CPU (user + system of the
   daemon's process group over the replay after its first 5 s, per wall second; and of it
   the daemon's own process, the rest being its contact worker's), peak
   resident memory (the largest of the group's processes), the latency of each ``contact``
   message during the 10-contact rounds (from the moment the replay fed the frame's last
   gateway record to the message at the subscriber; the frame is known by the newest cycle
   of a contact sampled in it, and placed by the message's ``t_sample``, less the *map
   lag*: how much later than the frame's gate start the daemon's map of mesh time puts it,
   about the quickest record's serial time, measured on the same recording in process),
   and the frames: complete by their records, by deadline, missed, late records; with the
   machine's load average and how late the replay fed its records at worst (a daemon that
   does not get its core falls behind the recording: its figures then say so). Periodic
   and event-based (threshold 30 counts). Then the daemon's core alone on the same
   recordings, in this process (pipeline and an estimate per frame, CPU per second of
   skin): what real speed needs of a core whatever else the machine runs.
3. **The estimate call.** ``ContactEstimator.estimate`` on one frame (clustering, problem
   set-up, fit, σ, light-touch intervals), CPU time of this thread: one contact on a 4×4
   and 10 contacts on the humanoid, on readings its model made and on readings it did not
   make (each element's overlap integrated on a 0.1 mm grid anchored at the disk, 3 % gain
   error per element and channel, 1 fF noise), with the elements flagged touched as the
   daemon's calibration flags them (a channel above its ``enter`` threshold). And the
   whole call the daemon's contact worker runs on the daemon's own 10-contact frames of the
   recordings of section 2 (the emulated chip's readings through the daemon's calibration:
   readings no model made), where the seam estimator, the tracker and the bounds by unknown
   elements add to the estimate.
"""

from __future__ import annotations

import os
from typing import cast

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from timing import table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout too
from cellbridge.daemon.shell.capture import CaptureWriter  # noqa: E402
from cellbridge.daemon.shell.skin_file import load_skin  # noqa: E402
from cellbridge.emulator.firmware.commands import Settings  # noqa: E402
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin  # noqa: E402
from cellbridge.emulator.mesh.skin_traffic import SkinTraffic  # noqa: E402
from cellbridge.emulator.realtime.realtime import reporting_arg  # noqa: E402
from cellbridge.emulator.world.world import Contact, World  # noqa: E402
from cellbridge.tactile import ContactEstimator, grid_layout, skin_response  # noqa: E402
from cellbridge.tactile.calibration import CalibrationConfig  # noqa: E402

from daemon_harness import Client, daemon, write_config  # noqa: E402

HUMANOID = ROOT / "cellbridge" / "skins" / "humanoid.toml"
RATE = 100
CLOCK = 50_000_000
T0 = 1_800_000_000.0  #: recorded host time of the generation's start (a replay shifts it to now)
ROUND, HOLD, FIRST = 3.0, 2.0, 2.0  #: s per round of presses, held, first press
NOISE = 1e-15
GRID = 1e-4
GAIN = 0.03
ENTER = float(cast(float, CalibrationConfig().enter))  #: F, the daemon's default touch threshold per channel (one for both)


def presses(skin, seconds: float, rng) -> list[Contact]:
    """Rounds of 10 simultaneous presses, each on another patch, from FIRST s on."""
    out = []
    t = FIRST
    while t + HOLD < seconds - 0.5:
        for pi in rng.choice(len(skin.patches), 10, replace=False):
            p = skin.patches[int(pi)]
            r, c = int(rng.integers(1, p.rows - 1)) if p.rows > 2 else 0, int(rng.integers(0, p.cols))
            x, y = skin.atlas[skin.row_of(skin.element_id(p.name, r, c))]
            dx, dy = rng.uniform(-0.015, 0.015, 2)
            out.append(Contact(t, HOLD, x + dx, y + dy, rng.uniform(2.0, 8.0), rng.uniform(0.012, 0.025)))
        t += ROUND
    return out


def generate(skin, reporting: str, seconds: float, into: Path) -> dict:
    """Capture files of every gateway; figures of the generation."""
    rng = np.random.default_rng(7)
    world = World(mesh_from_skin(skin), presses(skin, seconds, rng))
    traffic = SkinTraffic(skin, world, settings=Settings(reporting=reporting_arg(reporting)), seed=1)
    writers = {g: CaptureWriter(into / f"gw{g}.cbcap") for g in traffic.gateways}
    for w in writers.values():  # every line's replay shifted by one start: the gateways' offsets kept
        w.write(T0, b"")
    last: dict[int, float] = {}  # frame index -> s from its gate start to its last record
    c0 = time.process_time()
    nbytes = 0
    for k in range(int(round(seconds * RATE))):
        for t, g, data in sorted(traffic.frame(k)):
            writers[g].write(T0 + t, data)
            nbytes += len(data)
            last[k] = max(last.get(k, 0.0), t - k / RATE)
    cpu = time.process_time() - c0
    for w in writers.values():
        w.close()
    return {"cpu": cpu, "seconds": seconds, "bytes": nbytes, "last": last, "gateways": traffic.gateways,
            "counters": dict(traffic.counters)}


def cycle_mesh_rate(skin, seconds: float) -> float:
    """CPU s per virtual s of the cycle-level virtual-time mesh of the same skin."""
    from cellbridge.emulator.mesh.virtual import VirtualMesh

    vm = VirtualMesh(mesh_from_skin(skin), seed=1, random_epochs=True)
    c0 = time.process_time()
    vm.run(seconds)
    return (time.process_time() - c0) / seconds


def group_processes(pgid: int) -> dict[int, tuple[float, float, float]]:
    """``{pid: (VmRSS MiB, VmHWM MiB, user + system CPU s)}`` of the processes of a process
    group (the daemon's: its leader the daemon's own process, the others its contact worker,
    multiprocessing's helpers, a kernel compile's child)."""
    out: dict[int, tuple[float, float, float]] = {}
    tck = os.sysconf("SC_CLK_TCK")
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[2]) != pgid:
                continue
            status = dict(line.split(":", 1) for line in (d / "status").read_text().splitlines() if ":" in line)
            out[int(d.name)] = (int(status["VmRSS"].split()[0]) / 1024, int(status["VmHWM"].split()[0]) / 1024,
                                (int(fields[11]) + int(fields[12])) / tck)
        except (OSError, ValueError, IndexError, KeyError):
            continue
    return out


def group_cpu_rss(pgid: int) -> tuple[float, int, float]:
    """(user + system s, largest VmHWM kB, user + system s of the group's leader) of the
    processes of a process group (:func:`group_processes`)."""
    procs = group_processes(pgid)
    cpu = sum(v[2] for v in procs.values())
    rss = max((round(v[1] * 1024) for v in procs.values()), default=0)
    return cpu, rss, procs[pgid][2] if pgid in procs else 0.0


def frame_index(message: dict) -> int | None:
    """The index of the skin frame a ``contact`` message estimated, from a contact with an
    element sampled in that frame (its ``t_sample`` is the message's: its newest cycle is
    the frame's); None when every contact's readings are older (held: event-based)."""
    if message.get("t_sample") is None:
        return None
    fresh = [c for c in message["contacts"] if c.get("missed", 0) == 0 and c.get("t_sample") == message["t_sample"]
             and c.get("cycles")]
    return round(max(fresh[0]["cycles"]) * RATE / CLOCK) if fresh else None


def run_daemon(skin, gen: dict, into: Path, reporting: str, trace: list[list[object]] | None = None,
               map_lag: float = 0.0) -> list[object]:
    """The real daemon at real speed on the recording (see the module); ``trace``: run it
    through ``press_trace.py --light`` and append the breakdown row of its 10-contact
    frames (:func:`breakdown_row`); ``map_lag``: s the daemon's map puts a frame after its
    gate start (:func:`core_capacity`'s ``map_lags`` on the same recording), added back to
    each latency measured from the message's ``t_sample``."""
    links = [{"name": f"gw{g}", "url": f"replay:{into / f'gw{g}.cbcap'}", "replay_speed": 1.0,
              "wait_for_subscriber": True} for g in gen["gateways"]]
    cfg = into / "daemon.toml"
    ep = write_config(cfg, links, layout={"file": str(HUMANOID)}, health={"interval": 1.0})
    client = Client(ep, (b"contact", b"health"))
    lat: list[float] = []
    got_at: dict[float, float] = {}  # a 10-contact message's t_sample -> wall time it reached the subscriber
    contacts_max = 0
    health: dict = {}
    seconds = gen["seconds"]
    argv = None
    if trace is not None:
        argv = [sys.executable, str(Path(__file__).with_name("press_trace.py")), "--config", str(cfg),
                "--trace", str(into / "trace.msgpack"), "--light"]
    try:
        with daemon(cfg, stderr=into / "daemon.err", argv=argv) as proc:
            start = time.monotonic()
            cpu0 = None
            c_end = math.inf
            while time.monotonic() - start < seconds + 30:
                got = client.recv(1.0)
                now = time.time()
                el = time.monotonic() - start
                if cpu0 is None and el > 5.0:
                    cpu0, _, own0 = group_cpu_rss(proc.pid)
                    t_cpu0 = time.monotonic()
                if got is None:
                    if proc.poll() is not None:
                        break
                    continue
                topic, m = got
                if topic == "health":
                    health = m
                    if all(ln.get("replay_finished") for ln in m.get("links", {}).values()) and m.get("links"):
                        break
                    continue
                live = [c for c in m["contacts"] if c.get("missed", 0) == 0]
                k = frame_index(m)
                if not live or k is None:
                    continue
                t_in = (k / RATE) % ROUND
                if len(live) >= 10 and FIRST % ROUND + 0.3 < t_in < FIRST % ROUND + HOLD - 0.1 and k in gen["last"]:
                    # t_sample is the frame's gate start on the host's map, map_lag late:
                    # its last record was fed last[k] after the gate start
                    lat.append(now - (m["t_sample"] - map_lag) - gen["last"][k])
                    got_at[m["t_sample"]] = now
                contacts_max = max(contacts_max, len(live))
            cpu1, rss, own1 = group_cpu_rss(proc.pid)
            c_end = time.monotonic()
    finally:
        client.sub.close()
        client.ctx.term()
    if trace is not None:  # (the daemon stopped: its trace is written)
        trace.append(breakdown_row(reporting, into / "trace.msgpack", got_at))
    cpu_per_s = (cpu1 - cpu0) / (c_end - t_cpu0) if cpu0 is not None else math.nan
    own_per_s = (own1 - own0) / (c_end - t_cpu0) if cpu0 is not None else math.nan
    fr = health.get("frames", {})
    samples = gen["counters"].get("samples", 0) / gen["seconds"]
    la = np.array(lat) * 1e3
    late = max((ln.get("replay_late_max", 0.0) for ln in health.get("links", {}).values()), default=0.0)
    return [reporting, f"{os.getloadavg()[0]:.1f}", f"{samples:,.0f}", f"{cpu_per_s:.3f}", f"{own_per_s:.3f}", f"{rss / 1024:.0f}",
            f"{late * 1e3:.0f}", len(lat),
            f"{np.median(la):.2f}" if la.size else "-", f"{np.percentile(la, 99):.2f}" if la.size else "-",
            contacts_max, fr.get("frames_complete", "-"), fr.get("frames_by_deadline", "-"),
            fr.get("frames_missed", "-"), fr.get("late_records", "-")]


#: the steps of :func:`breakdown_row`, each from the end of the one before
STEPS = ("read late", "frame complete → look", "look → job submitted", "submitted → worker began", "worker's estimate",
         "worker ended → result in the loop", "result → published", "published → subscriber")


def breakdown_row(reporting: str, path: Path, got_at: dict[float, float]) -> list[object]:
    """Where the 10-contact frames' latency went, from a ``press_trace.py --light`` trace and
    ``got_at`` (each message's ``t_sample`` and the wall time it reached the subscriber): per
    message, the host times of each step from the read that completed its frame (its due
    time in the replay, then when the pipeline took it) to the subscriber; each step's median
    and p99 in ms, and the whole."""
    import msgpack

    with open(path, "rb") as f:
        tr = msgpack.unpack(f, strict_map_key=False)
    off = tr["wall_offset"][0]
    # frame's host time -> (the read's time, when the layout took it): a paced replay's read
    # carries its due time, and may be fed after it (the loop busy)
    completed = {k[1]: (k[0], k[3]) for k in tr["k"]}
    looks = sorted(tuple(e) for e in tr["e"] if e[2] is not None)  # (began, ended, frame's host time)
    jobs = sorted(tuple(x) for x in tr.get("x", []))  # (submitted, began, ended, result in the loop)
    published = {p[1]: p[0] for p in tr["p"]}  # t_sample -> when handed to ZeroMQ
    steps: list[list[float]] = [[] for _ in range(len(STEPS) + 1)]
    for t_sample, recv in got_at.items():
        pub = published.get(t_sample)
        e = None if pub is None else next((e for e in looks if e[0] <= pub <= e[1]), None)
        done = None if e is None else completed.get(e[2])
        x = None if e is None else next((j for j in jobs if e[0] <= j[0] <= e[1]), None)
        if pub is None or e is None or done is None or x is None:
            continue
        times = [done[0], done[1], e[0], x[0], x[1], x[2], x[3], pub, recv - off]
        for i in range(len(STEPS)):
            steps[i].append(times[i + 1] - times[i])
        steps[-1].append(times[-1] - times[0])
    cells: list[object] = [reporting, len(steps[-1])]
    for v in steps:
        a = np.array(v) * 1e3
        cells.append(f"{np.median(a):.2f} / {np.percentile(a, 99):.2f}" if a.size else "-")
    return cells


def warm_calibration() -> None:
    """The calibrator's compiled step warm, as the daemon has it before its links start; a
    revision without it (``bench_humanoid_core --against``) steps with numpy (looked for in
    the package imported: the editable install's finder would find this checkout's)."""
    import cellbridge.tactile

    if (Path(cellbridge.tactile.__file__).parent / "calibration_kernel.py").exists():
        from cellbridge.tactile.calibration_kernel import warm_up

        warm_up()


def core_capacity(skin, gen: dict, into: Path, reporting: str, topics: tuple[str, ...] | None = None,
                  map_lags: list[float] | None = None, calls: dict[int, list[float]] | None = None) -> list[object]:
    """The daemon's core on the same recording, in this process: the pipeline fed every read
    in order of arrival, a contact estimate per frame (inline, as the worker runs it); CPU
    per second of skin (what real speed needs of a core, whatever else the machine runs).
    The shell's share (asyncio, the replay's pacing, ZeroMQ) is left out. ``topics``: the
    topics subscribed (the pipeline builds only their messages); None: every topic.
    ``map_lags``: appended, for every estimated frame :func:`frame_index` names, how much
    later than its gate start the daemon's map put it (s): the host learns a frame's time
    from its records' arrivals, and a record arrives its serial time after the gateway began
    writing it, so the map is late by about the quickest record's serial time.
    ``calls``: appended, per number of contacts a frame's estimate found (not missed), the
    CPU (s) of each call the worker would run (:meth:`ContactWorker.estimate_now`: seam
    estimator, tracker, bounds by unknown elements), on the daemon's own frames."""
    import hashlib
    import heapq
    import logging

    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.messages import Publish
    from cellbridge.daemon.core.pipeline import Pipeline
    from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
    from cellbridge.daemon.shell.publisher import pack
    from cellbridge.daemon.shell.replay_source import read_records

    warm_calibration()
    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in gen["gateways"]]
    p = Pipeline(parse_config({"link": links}), skin.layout())
    p.surface = skin
    p.want(None if topics is None else set(topics))
    w = ContactWorker(logging.getLogger("bench_humanoid"), InlineExecutor)
    streams = [((t, g, d) for t, d in read_records(into / f"gw{g}.cbcap", "x")) for g in gen["gateways"]]
    feed = est = 0.0
    estimates = 0
    tick = 0.0
    digest = hashlib.sha256()
    for t, g, data in heapq.merge(*streams):
        c0 = time.thread_time()
        out = p.feed(f"gw{g}", data, t)
        c1 = time.thread_time()
        if t >= tick:
            out += p.tick(t)
            tick = t + 0.1
        job = p.contact_job(t)
        frame = None
        if job is not None:
            e0 = time.thread_time()
            found = w.estimate_now(job)
            if calls is not None:
                live = sum(1 for c in found or () if c.get("missed", 0) == 0)
                calls.setdefault(live, []).append(time.thread_time() - e0)
            frame = p.contact_frame(job, found)
            out.append(frame)
            estimates += 1
        c2 = time.thread_time()
        if map_lags is not None and frame is not None:
            k = frame_index(frame.payload)
            if k is not None:
                map_lags.append(frame.payload["t_sample"] - p.wall_offset - (T0 + k / RATE))
        feed, est = feed + c1 - c0, est + c2 - c1
        for m in out:  # every output, outside the CPU measured
            digest.update(type(m).__name__.encode())
            digest.update(pack(m.payload) if isinstance(m, Publish) else repr(m).encode())
    body = p.health_body(t)
    digest.update(pack(body))
    fr = body["frames"]
    secs = gen["seconds"]
    return [reporting, f"{feed / secs:.3f}", f"{est / secs:.3f}", f"{(feed + est) / secs:.3f}", estimates,
            fr["frames_complete"], fr["frames_by_deadline"], fr["frames_missed"], fr["late_records"],
            digest.hexdigest()[:16]]


def grid_response(lay, contact):
    """(ΔC1, ΔC2) of one disk, each element's overlap counted on a 0.1 mm grid of cell
    centres anchored at the disk's centre: an integration independent of the model's."""
    from cellbridge.tactile.element import sensitivity

    x, y, f, d = contact
    r = 0.5 * d
    g1, g2 = sensitivity(np.array([f / (math.pi * r * r)]))
    k = np.arange(-math.ceil(r / GRID) - 1, math.ceil(r / GRID) + 2) * GRID
    px, py = np.meshgrid(x + k, y + k, indexing="ij")
    inside = (px - x) ** 2 + (py - y) ** 2 <= r * r
    pts = np.stack([px[inside], py[inside]], axis=-1)
    # lay.element_at's rule (inside or on the border, the lowest index wins) among the elements
    # that reach the disk's square only: on the humanoid's 1 144 elements, comparing every
    # point with every element made this bench's frames take minutes
    b = lay.bounds
    near = np.flatnonzero((b[:, 0] <= x + r) & (b[:, 2] >= x - r) & (b[:, 1] <= y + r) & (b[:, 3] >= y - r))
    bn = b[near]
    hit = ((pts[:, None, 0] >= bn[None, :, 0]) & (pts[:, None, 0] <= bn[None, :, 2])
           & (pts[:, None, 1] >= bn[None, :, 1]) & (pts[:, None, 1] <= bn[None, :, 3]))
    idx = np.where(hit.any(axis=1), near[hit.argmax(axis=1)], -1) if near.size else np.full(len(pts), -1)
    area = np.bincount(idx[idx >= 0], minlength=lay.n) * GRID * GRID
    return area * g1[0], area * g2[0]


def near_cut(skin, x: float) -> bool:
    """Whether an element at atlas ``x`` lies at either end of a band (a wrap's cut)."""
    return any(abs(x - b.x0) < skin.side or abs(x - (b.x0 + b.period)) < skin.side for b in skin.bands)


def estimate_rows(skin, n: int = 200) -> list[list[object]]:
    rng = np.random.default_rng(11)
    rows: list[list[object]] = []
    for name, lay, k in (("4×4, 1 contact", grid_layout(4, 4), 1), ("humanoid, 10 contacts", skin.layout(), 10)):
        est = ContactEstimator(lay, noise=NOISE)
        for made in ("own model", "not its model (grid, 3 % gain)"):
            frames, found = [], []
            for _ in range(n):
                picks = rng.choice(lay.n, k, replace=False) if k > 1 else [int(rng.integers(lay.n))]
                while k > 1 and (min(np.linalg.norm(lay.centres[a, :2] - lay.centres[b, :2])
                                     for i, a in enumerate(picks) for b in picks[i + 1:]) < 3.5 * lay.side
                                 or any(near_cut(skin, lay.centres[a, 0]) for a in picks)):
                    # presses apart, and none across a band's cut (the atlas's estimator reads one
                    # as two; the daemon's seam estimator joins them): k contacts, not more nor fewer
                    picks = rng.choice(lay.n, k, replace=False)
                cs = [[*(lay.centres[r, :2] + rng.uniform(-0.012, 0.012, 2)), rng.uniform(2.0, 10.0),
                       rng.uniform(0.010, 0.025)] for r in picks]
                if made == "own model":
                    d1, d2 = skin_response(lay, cs)
                else:
                    d1, d2 = np.zeros(lay.n), np.zeros(lay.n)
                    for c in cs:
                        a, b = grid_response(lay, c)
                        d1, d2 = d1 + a, d2 + b
                    g = 1.0 + rng.normal(0.0, GAIN, (2, lay.n))
                    d1, d2 = d1 * g[0], d2 * g[1]
                d1, d2 = d1 + rng.normal(0, NOISE, lay.n), d2 + rng.normal(0, NOISE, lay.n)
                # touched as the daemon's calibration flags it (a channel above ``enter``):
                # the estimator's own default (3 noise σ per channel) is for a few elements;
                # on 1 144 it lets about three noise readings a frame through as light touches
                frames.append((d1, d2, (d1 > ENTER) | (d2 > ENTER)))
            for f in frames[:20]:
                est.estimate(*f)  # compiled kernels loaded, every path warm
            cpu = []
            for f in frames:
                c0 = time.thread_time()
                found.append(len(est.estimate(*f)))
                cpu.append(time.thread_time() - c0)
            ms = np.array(cpu) * 1e3
            rows.append([name, made, n, f"{np.mean(found):.2f}", f"{np.median(ms):.3f}", f"{np.percentile(ms, 99):.3f}",
                         "0.5" if k == 1 else "4"])
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="length of each recording (default 120)")
    ap.add_argument("--quick", action="store_true", help="40 s recordings, a shorter cycle-level comparison")
    ap.add_argument("--skip-daemon", action="store_true", help="generation and the estimate call only")
    ap.add_argument("--estimate-only", action="store_true",
                    help="the estimate call's table (section 3) alone: no generation, no daemon")
    ap.add_argument("--trace", action="store_true",
                    help="run the daemon through bench/press_trace.py --light and print where its 10-contact "
                         "frames' latency went (the trace costs the daemon some CPU: its CPU figure is then high)")
    a = ap.parse_args()
    seconds = 40.0 if a.quick else a.seconds
    skin = load_skin(HUMANOID)
    print(f"{HUMANOID.name}: {skin.n} elements, {len(skin.gateways)} gateways, {len(skin.patches)} patches, "
          f"{len({p.link for p in skin.patches})} links")
    gen_rows: list[list[object]] = []
    daemon_rows: list[list[object]] = []
    flat_rows: list[list[object]] = []
    own_rows: list[list[object]] = []
    trace_rows: list[list[object]] | None = [] if a.trace else None
    if a.estimate_only:
        estimate_table(skin, a.quick)
        return 0
    with tempfile.TemporaryDirectory(prefix="bench_humanoid.") as tmp:
        for reporting in ("periodic", "event:30"):
            into = Path(tmp) / reporting.replace(":", "")
            into.mkdir()
            g = generate(skin, reporting, seconds, into)
            gen_rows.append([f"frame-level, {reporting}", f"{seconds:.0f}", f"{g['cpu']:.1f}",
                             f"{g['cpu'] / seconds:.3f}", f"{seconds / g['cpu']:.1f}",
                             f"{g['counters'].get('samples', 0) / seconds:,.0f}",
                             f"{g['counters'].get('unchanged', 0) / seconds:,.0f}",
                             f"{g['bytes'] / seconds / len(g['gateways']) / 1e3:.1f}"])
            if not a.skip_daemon:
                lags: list[float] = []
                calls: dict[int, list[float]] = {}
                flat_rows.append(core_capacity(skin, g, into, reporting, map_lags=lags, calls=calls))
                ms = np.array(calls.get(10, [])) * 1e3
                own_rows.append([reporting, ms.size, f"{np.median(ms):.3f}" if ms.size else "-",
                                 f"{np.percentile(ms, 99):.3f}" if ms.size else "-", "4"])
                daemon_rows.append(run_daemon(skin, g, into, reporting, trace_rows, float(np.median(lags))))
                daemon_rows[-1].insert(10, f"{1e3 * float(np.median(lags)):.2f}")
    short = 0.05 if a.quick else 0.2
    rate = cycle_mesh_rate(skin, short)
    gen_rows.append([f"cycle-level mesh (virtual time), {short} s", f"{short}", f"{rate * short:.1f}",
                     f"{rate:.1f}", f"{1 / rate:.3f}", "-", "-", "-"])
    table("Generation of the humanoid's traffic (one core; CPU of this process)",
          ["generator", "virtual s", "CPU s", "CPU s per virtual s", "× real time", "samples/s", "unchanged/s",
           "kB/s per gateway line"], gen_rows)
    if daemon_rows:
        table("The daemon at real speed on the humanoid (22 replay links at recorded speed; targets: periodic CPU "
              "≤ 1 core, event-based ≤ 0.25, RSS ≤ 250 MiB, p99 ≤ 10 ms, no frame lost)",
              ["reporting", "load avg", "samples/s", "CPU (cores)", "of it the daemon's own process", "peak RSS MiB", "replay fed late, max ms", "10-contact frames", "latency median ms",
               "latency p99 ms", "map lag ms", "most contacts", "frames complete", "by deadline", "missed", "late records"],
              daemon_rows)
    if trace_rows:
        table("Where the 10-contact frames' latency went (the traced daemon; ms, median / p99; each step from "
              "the end of the one before, the first from the due time of the read that completed the frame)",
              ["reporting", "frames", *STEPS, "read due → subscriber"], trace_rows)
    if flat_rows:
        table("The daemon's core per second of skin: the same recordings through the pipeline and an estimate per "
              "frame, in this process (CPU of this thread per recorded s; targets: periodic ≤ 1, event-based ≤ 0.25)",
              ["reporting", "ingest CPU s/s", "estimates CPU s/s", "together", "estimates", "frames complete",
               "by deadline", "missed", "late records", "outputs (sha256)"], flat_rows)
    if own_rows:
        table("The estimate on the daemon's own frames: its 10-contact frames of the recordings above (the "
              "emulated chip's readings through the daemon's calibration), the whole call its contact worker runs "
              "(seam estimator, tracker, bounds by unknown elements; CPU of this thread, ms)",
              ["reporting", "frames", "CPU median ms", "CPU p99 ms", "target ms"], own_rows)
    estimate_table(skin, a.quick)
    return 0


def estimate_table(skin, quick: bool) -> None:
    """Section 3's table (60 frames per row with ``quick``, else 200)."""
    table("ContactEstimator.estimate, one frame (CPU of this thread; target medians: 0.5 ms one contact on 4×4, "
          "4 ms ten contacts on the humanoid)",
          ["skin", "readings", "frames", "contacts found (mean)", "CPU median ms", "CPU p99 ms", "target ms"],
          estimate_rows(skin, 60 if quick else 200))


if __name__ == "__main__":
    raise SystemExit(main())
