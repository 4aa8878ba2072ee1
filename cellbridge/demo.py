"""``cellbridge demo``: the whole chain on one machine, as a robot would run it.

An emulated 4×4 skin (one process per bridge, ``cellbridge mesh up``) serves its gateway
on a pseudo-terminal; ``cellbridge daemon`` opens that pty exactly as it would open
``/dev/ttyUSB0``, and this command subscribes to the daemon's ZeroMQ ``contact`` topic,
presses on the skin where two elements meet, and compares what the daemon reports
with what was pressed. It is the first thing to run on a new machine (``make demo``)
and doubles as the end-to-end check of the test suite (``--check``).

Every process it starts lives in its own process group and is stopped on the way out,
also on Ctrl-C or an error.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import msgpack
import zmq

#: s for 'mesh up' to print its gateway line: a guard against a hung start, not a pace (a
#: 4x4 starts 18 interpreters first; 30 s ran out on a busy 2-core machine)
GATEWAY_TIMEOUT = 90.0
START_TIMEOUT = 120.0  # s for the daemon to see every bridge calibrated (first run compiles kernels)
#: daemons started on fresh ports when another program took one between its choice and the bind
BIND_TRIES = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__.split("\n\n")[0].replace("``cellbridge demo``: the", "The") + (
        " Starts an emulated 4×4 skin and the daemon on its gateway, presses where two"
        " elements meet, and prints the contact the daemon published next to the press."
    )
    parser.add_argument("--x", type=float, default=0.057, help="press centre x in metres (default 0.057: across the seam at 0.06)")
    parser.add_argument("--y", type=float, default=0.040, help="press centre y in metres (default 0.040: the row's centre line)")
    parser.add_argument("--force", type=float, default=3.0, help="press force in newtons (default 3)")
    parser.add_argument("--diameter", type=float, default=0.02, help="press diameter in metres (default 0.02)")
    parser.add_argument("--duration", type=float, default=3.0, help="press duration in seconds (default 3)")
    parser.add_argument("--rows", type=int, default=4, help="skin rows (default 4)")
    parser.add_argument("--cols", type=int, default=4, help="skin columns (default 4)")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 unless the contact is within 1 mm and 5 %% of the press")
    parser.add_argument("--defaults", action="store_true",
                        help="run the skin and the daemon with their own defaults, as by hand ('mesh up' "
                             "periodic at 100 Hz, the daemon's calibration from 50 readings) instead of "
                             "the demo's event-based skin and 10-reading calibration")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.add_argument("--keep", action="store_true",
                        help="keep the working folder (mesh, config, logs); its path is printed on stderr, and "
                             "with --json is the result's 'kept'")


#: The demo's listening ports come from [LISTEN_FLOOR, the kernel's ephemeral range): a port
#: in that range, free when chosen, can be taken a moment later as the local end of any
#: process's outgoing connection before the emulator or daemon binds it (a demo run on a
#: busy machine lost its medium's port that way and stopped before the press).
LISTEN_FLOOR = 20_000


def ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (32768 where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _free_port() -> int:
    return _free_port_block(1)


def _free_port_block(n: int) -> int:
    """A base port with ``n`` consecutive free ports on 127.0.0.1 after it, below the
    ephemeral range (see ``LISTEN_FLOOR``; any free block where that range leaves no room).
    RuntimeError when 50 tries found none."""
    rng = random.SystemRandom()
    top = ephemeral_low() - n
    for _ in range(50):
        if top - LISTEN_FLOOR >= 1000:
            base = rng.randrange(LISTEN_FLOOR, top)
        else:
            with socket.socket() as probe:
                probe.bind(("127.0.0.1", 0))
                base = int(probe.getsockname()[1])
        socks = []
        try:
            for k in range(n):
                s = socket.socket()
                socks.append(s)
                s.bind(("127.0.0.1", base + k))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no block of free TCP ports on 127.0.0.1")


def _stop(proc: subprocess.Popen[Any], grace: float = 10.0) -> None:
    """SIGTERM the process group, then SIGKILL what is left after ``grace`` seconds."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(grace)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(5)


@contextmanager
def _group(cmd: list[str], **kw: Any) -> Iterator[subprocess.Popen[Any]]:
    """``cmd`` in its own session, stopped on exit; told to stop (SIGTERM) if the demo dies
    first, too: a demo killed by a timeout left its skin and its daemon running."""
    from cellbridge.emulator.realtime.realtime import die_with_parent

    proc = subprocess.Popen(cmd, start_new_session=True, preexec_fn=die_with_parent, **kw)
    try:
        yield proc
    finally:
        _stop(proc)


def _cellbridge(*args: str) -> list[str]:
    return [sys.executable, "-m", "cellbridge", *args]


def gateway_line(proc: subprocess.Popen[Any]) -> list[str]:
    """The words of the first ``gateway <id> <device> ...`` line ``mesh up`` prints. Raises
    RuntimeError when it ends first or prints none within GATEWAY_TIMEOUT: read from the
    pipe as bytes come (a blocking line read waited for ever on a 'mesh up' that went
    silent, whatever the timeout said)."""
    deadline = time.monotonic() + GATEWAY_TIMEOUT
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    got = b""
    while (left := deadline - time.monotonic()) > 0:
        if not select.select([fd], [], [], min(left, 0.5))[0]:
            continue
        chunk = os.read(fd, 4096)
        if not chunk:
            raise RuntimeError(f"'mesh up' ended (status {proc.wait()}) before naming its gateway")
        got += chunk
        *lines, got = got.split(b"\n")
        for line in lines:
            parts = line.decode(errors="replace").split()
            if len(parts) >= 3 and parts[0] == "gateway":
                return parts
    raise RuntimeError(f"'mesh up' named no gateway within {GATEWAY_TIMEOUT:.0f} s")


def _warm_kernels() -> None:
    """Compile the contact-fit kernels and the calibrator's step here, once, into numba's cache.

    The daemon would otherwise compile them on its first contact (about half a minute on
    a fresh install), and the press would be over before the daemon could report it; and
    the calibrator's step at its start, in a thread that holds its loop back meanwhile."""
    from cellbridge.tactile import ContactEstimator, calibration_kernel, grid_layout

    calibration_kernel.warm_up()

    layout = grid_layout(2, 2)
    est = ContactEstimator(layout)
    import numpy as np

    est.estimate(np.full(4, 1e-13), np.full(4, 5e-14))


def _recv(sub: zmq.Socket, timeout: float) -> tuple[str, dict[str, Any]] | None:
    if not sub.poll(int(timeout * 1000)):
        return None
    topic, payload = sub.recv_multipart()
    return topic.decode(), msgpack.unpackb(payload)


def _wait_ready(sub: zmq.Socket, n: int, daemon: subprocess.Popen[Any], mesh: subprocess.Popen[Any]) -> None:
    deadline = time.monotonic() + START_TIMEOUT
    while time.monotonic() < deadline:
        for name, proc in (("daemon", daemon), ("mesh up", mesh)):
            if proc.poll() is not None:
                raise RuntimeError(f"{name} ended with status {proc.returncode} during start-up")
        msg = _recv(sub, 1.0)
        if msg and msg[0] == "health":
            cal = msg[1].get("layout", {}).get("calibration", {})
            if cal.get("ready", 0) >= n:
                return
    raise RuntimeError(f"the daemon did not see {n} calibrated elements within {START_TIMEOUT:.0f} s")


Collected = tuple[list[dict[str, Any]], int, dict[int, int], dict[str, int]]


def _press_and_collect(args: argparse.Namespace, base_port: int, sub: zmq.Socket) -> Collected:
    """Press, and collect what the daemon published meanwhile: the contacts (without the
    ones kept through missed frames), the number of ``contact`` messages, in how many of
    those each element was listed unknown (frames the skin did not deliver whole), and
    how its health's skin frame counters (``frames_complete``, ``frames_by_deadline``,
    ``unknown_element_frames``) moved from its first health message in the window to its last."""
    subprocess.run(_cellbridge("press", str(args.x), str(args.y), "--force", str(args.force),
                               "--diameter", str(args.diameter), "--duration", str(args.duration),
                               "--base-port", str(base_port)), check=True, timeout=30, stdout=subprocess.DEVNULL)
    seen: list[dict[str, Any]] = []
    messages = 0
    unknown: dict[int, int] = {}
    frames: list[dict[str, Any]] = []
    end = time.monotonic() + args.duration + 1.0
    while time.monotonic() < end:
        msg = _recv(sub, 0.2)
        if msg and msg[0] == "contact":
            messages += 1
            for e in msg[1].get("unknown") or ():
                unknown[e] = unknown.get(e, 0) + 1
            seen.extend(c for c in msg[1]["contacts"] if c.get("missed", 0) == 0)
        elif msg and msg[0] == "health" and isinstance(msg[1].get("frames"), dict):
            frames.append(msg[1]["frames"])
    skin: dict[str, int] = {}
    for key in ("frames_complete", "frames_by_deadline", "unknown_element_frames"):
        counts = [f[key] for f in frames if isinstance(f.get(key), int)]
        if len(counts) >= 2:
            skin[key] = counts[-1] - counts[0]
    return seen, messages, unknown, skin


def _summarise(args: argparse.Namespace, collected: Collected) -> dict[str, Any]:
    """The press's steady part: the second half of the reports of the longest-lived id.

    Besides the median of those (``reported``), ``known`` is the median of the steady
    reports that listed no unknown element near them: what the daemon stated while the
    skin delivered every reading it needed. ``skin_whole`` says the skin delivered every
    frame of the press whole (no ``contact`` message listed an unknown element, and the
    daemon's health counted no element-frame without a reading meanwhile): only
    then can the press's every report be held to 1 mm and 5 %; an emulated skin starved of
    CPU (a busy machine) falls behind real time and loses records, and then the reports
    list what they do not know. ``skin_frames`` is how the daemon's health counted the
    skin's frames meanwhile (complete, by deadline, unknown element-frames)."""
    contacts, messages, unknown, skin = collected
    out: dict[str, Any] = {"pressed": {"x": args.x, "y": args.y, "force": args.force, "diameter": args.diameter},
                           "reports": len(contacts),
                           "with_unknown": sum(1 for c in contacts if c.get("unknown_near")),
                           "untrue": sum(1 for c in contacts if _untrue(args, c)),
                           "messages": messages, "unknown_elements": {str(e): n for e, n in sorted(unknown.items())}, "skin_frames": skin,
                           "skin_whole": messages > 0 and not unknown and not skin.get("unknown_element_frames")}
    if not contacts:
        return out
    ids = [c["id"] for c in contacts]
    main = max(set(ids), key=ids.count)
    mine = [c for c in contacts if c["id"] == main]
    steady = mine[len(mine) // 2:]
    out["untrue_force"] = sum(1 for c in steady if _untrue_force(args, c))

    def median(key: str) -> float:
        v = sorted(float(c[key]) for c in steady)
        return v[len(v) // 2]

    got: dict[str, Any] = {k: median(k) for k in ("x", "y", "force", "diameter", "centroid_x", "centroid_y",
                                                  "sigma_x", "sigma_y")}
    got["observable"] = steady[-1].get("observable")
    known = [c for c in steady if not c.get("unknown_near")]
    if known:
        out["known"] = {"reports": len(known), **{k: sorted(float(c[k]) for c in known)[len(known) // 2]
                                                   for k in ("x", "y", "force")}}
        kg = out["known"]
        kg.update(position_error_mm=1e3 * math.hypot(kg["x"] - args.x, kg["y"] - args.y),
                  force_error_pct=100 * abs(kg["force"] - args.force) / args.force)
    out.update(reported=got, ids=sorted(set(ids)),
               position_error_mm=1e3 * math.hypot(got["x"] - args.x, got["y"] - args.y),
               centroid_error_mm=1e3 * math.hypot(got["centroid_x"] - args.x, got["centroid_y"] - args.y),
               force_error_pct=100 * abs(got["force"] - args.force) / args.force)
    return out


def _untrue_force(args: argparse.Namespace, c: dict[str, Any]) -> bool:
    """A steady report (the press's second half: no frame of it straddles the press's step)
    that states a wrong force as known: off the press by more than 5 % and 3 of its own σ,
    with no unknown element listed that would explain it."""
    if c.get("unknown_near"):
        return False
    sigma = c.get("sigma_force")
    sigma = float(sigma) if isinstance(sigma, (int, float)) and math.isfinite(sigma) else 0.0
    return abs(float(c["force"]) - args.force) > max(0.05 * args.force, 3 * sigma)


def _untrue(args: argparse.Namespace, c: dict[str, Any]) -> bool:
    """A report that states a wrong position as known: off the press by more than 1 mm and
    3 of its own σ on an axis, with no unknown element listed that would explain it."""
    if c.get("unknown_near"):
        return False
    for axis, true in (("x", args.x), ("y", args.y)):
        off = abs(float(c[axis]) - true)
        if off > max(1e-3, 3 * float(c.get("sigma_" + axis, 0.0))):
            return True
    return False


def _print_table(r: dict[str, Any]) -> None:
    p = r["pressed"]
    if "reported" not in r:
        print("no contact was reported for the press")
        _print_skin(r)
        return
    g = r["reported"]
    print(f"{'':22}{'pressed':>12}{'reported':>12}")
    obs = g.get("observable") or [True, True]
    for k, axis in enumerate("xy"):
        note = f"  ± {1e3 * g['sigma_' + axis]:.3f}" + ("" if obs[k] else "  (inside one element: not resolved, centre of the range)")
        print(f"{axis + ' (mm)':22}{1e3 * p[axis]:12.2f}{1e3 * g[axis]:12.2f}{note}")
    print(f"{'force (N)':22}{p['force']:12.3f}{g['force']:12.3f}")
    print(f"{'diameter (mm)':22}{1e3 * p['diameter']:12.2f}{1e3 * g['diameter']:12.2f}")
    print(f"position error {r['position_error_mm']:.2f} mm (the paper's centroid: "
          f"{r['centroid_error_mm']:.1f} mm), force error {r['force_error_pct']:.2f} %, "
          f"{r['reports']} reports, contact ids {r['ids']}")
    print(f"{r['with_unknown']} reports listed unknown elements; {r['untrue']} stated a position "
          f"off by more than 1 mm and 3 σ with none listed, {r.get('untrue_force', 0)} (of the press's "
          "second half) a force off by more than 5 % and 3 σ")
    _print_skin(r)


def _print_skin(r: dict[str, Any]) -> None:
    """Whether the skin delivered the press's frames whole, and what the daemon said while it did."""
    if r.get("skin_whole"):
        return
    listed = ", ".join(f"{e} in {n}" for e, n in r.get("unknown_elements", {}).items()) or "none"
    lost = r.get("skin_frames", {}).get("unknown_element_frames", 0)
    print(f"the skin did not deliver every frame whole: of {r.get('messages', 0)} contact messages, "
          f"these listed elements unknown: {listed}; element-frames without a reading meanwhile: {lost} "
          "(an emulated skin on a busy machine falls behind real time; health says how: "
          "frames_by_deadline, unknown_element_frames)")
    k = r.get("known")
    if k:
        print(f"reports that knew every element near them: {k['reports']}, position error "
              f"{k['position_error_mm']:.2f} mm, force error {k['force_error_pct']:.2f} %")


def _within(r: dict[str, Any]) -> bool:
    return "reported" in r and r["position_error_mm"] <= 1.0 and r["force_error_pct"] <= 5.0


def _daemon_and_press(args: argparse.Namespace, work: Path, device: str, pub: str, ctl: str, base_port: int,
                      mesh: subprocess.Popen[Any], n: int, say: Callable[..., None]) -> dict[str, Any] | None:
    """Start the daemon on the gateway's ``device`` with ``pub`` and ``ctl``, wait until
    every element is calibrated, press and summarise; None when the daemon ended at start-up
    because another program bound one of its ports first (the ports were free when chosen,
    and the daemon binds them seconds later: on a busy machine something else may take one
    meanwhile). Raises RuntimeError for any other start-up failure."""
    config = work / "daemon.toml"
    # baselines from 10 quiet readings (the default 50 take 50 s at the skin's 1 s
    # heartbeat; the emulated counters' noise is about one count)
    config.write_text(f'[pub]\nendpoint = "{pub}"\n\n[control]\nendpoint = "{ctl}"\n\n'
                      f'[daemon]\nlog_format = "text"\n\n'
                      + ("" if args.defaults else "[calibration]\nn_baseline = 10\n\n")
                      + f'[[link]]\nname = "gateway"\nurl = "{device}"\n')
    log = work / "daemon.log"
    start = log.stat().st_size if log.exists() else 0
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    for topic in (b"contact", b"health"):
        sub.setsockopt(zmq.SUBSCRIBE, topic)
    sub.connect(pub)
    try:
        with _group(_cellbridge("daemon", "--config", str(config)), stderr=open(log, "a")) as daemon:
            try:
                _wait_ready(sub, n, daemon, mesh)
            except RuntimeError:
                if daemon.poll() is not None and _bind_refused(log, start):
                    return None
                raise
            say(f"all {n} elements calibrated; pressing {args.force} N with a {1e3 * args.diameter:.0f} mm "
                f"disk at ({1e3 * args.x:.1f}, {1e3 * args.y:.1f}) mm for {args.duration} s ...")
            return _summarise(args, _press_and_collect(args, base_port, sub))
    finally:
        sub.close()


def _bind_refused(log: Path, start: int) -> bool:
    """Whether the daemon's log from byte ``start`` on says an endpoint was in use."""
    with open(log, "rb") as f:
        f.seek(start)
        text = f.read().decode(errors="replace")
    return "cannot bind" in text and "Address already in use" in text


def _problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the skin or the press asked for, as 'mesh gen' and 'press' say it,
    or None. Asked before anything starts: a press beside the skin or of a negative force
    was refused only after the skin had booted and calibrated, a minute later, and a
    --rows 0 was a traceback."""
    from cellbridge.emulator.mesh import meshgen
    from cellbridge.emulator.mesh.mesh import MeshError
    from cellbridge.emulator.world.world import ScenarioError, check_on_skin, contact_from_mapping

    try:
        mesh = meshgen.grid(args.rows, args.cols)
        press = {"start": 0.0, "duration": args.duration, "position": [args.x, args.y], "force": args.force,
                 "diameter": args.diameter}
        check_on_skin(mesh, contact_from_mapping(press, "press"), "press")
    except (MeshError, ScenarioError) as exc:
        return str(exc)
    return None


def run(args: argparse.Namespace) -> int:
    from cellbridge.emulator.mesh import meshgen
    from cellbridge.emulator.mesh.mesh import mesh_to_toml

    problem = _problem(args)
    if problem is not None:
        print(f"cellbridge demo: {problem}", file=sys.stderr)
        return 2
    say = (lambda *a: None) if args.json else (lambda *a: print(*a, file=sys.stderr, flush=True))
    work = Path(tempfile.mkdtemp(prefix="cellbridge-demo-"))
    try:
        say("compiling the contact-fit kernels (a first run on a machine takes about half a minute) ...")
        _warm_kernels()
        mesh_file = work / "skin.toml"
        mesh_file.write_text(mesh_to_toml(meshgen.grid(args.rows, args.cols)))
        base_port = _free_port_block(3)
        n = args.rows * args.cols
        say(f"starting an emulated {args.rows}x{args.cols} skin: {n} bridge processes, medium and world ...")
        # event-based reporting, as a large skin runs: an idle element sends a heartbeat, a
        # pressed one every sample; periodic 100 Hz from 16 bridges crowds the gateway's cell
        reporting = () if args.defaults else ("--reporting", "event:40")
        with _group(_cellbridge("mesh", "up", str(mesh_file), "--base-port", str(base_port), *reporting),
                    stdout=subprocess.PIPE, stderr=open(work / "mesh.log", "w"), text=True) as mesh:
            device = gateway_line(mesh)[2]
            for attempt in range(1, BIND_TRIES + 1):
                pub, ctl = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
                say(f"gateway on {device}; starting the daemon on it (pub {pub}) ...")
                outcome = _daemon_and_press(args, work, device, pub, ctl, base_port, mesh, n, say)
                if outcome is not None:
                    result = outcome
                    break
                if attempt == BIND_TRIES:
                    raise RuntimeError(f"the daemon's ports were taken before it could bind them, {BIND_TRIES} times")
                say("another program took the daemon's ports before it bound them; again on others ...")
        if args.keep:
            result["kept"] = str(work)
        if args.json:
            print(json.dumps(result))
        else:
            _print_table(result)
        if args.keep:  # (with --json too, where say is silent: the one answer --keep asked for)
            print(f"working folder kept: {work}", file=sys.stderr, flush=True)
        return 0 if (_within(result) or not args.check) else 1
    except (RuntimeError, subprocess.SubprocessError) as exc:
        print(f"cellbridge demo: {exc} (logs in {work})", file=sys.stderr)
        args.keep = True
        return 1
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
