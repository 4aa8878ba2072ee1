"""``cellbridge robot``: a simulated robot touches its emulated skin; the daemon's contacts
are scored against what MuJoCo says touched it.

``run`` scripts a scenario (single presses anywhere, across wrap seams and across the
seam of two patches of one link, slides, two at once) on the arm of
:mod:`cellbridge.emulator.world.robot_world`, simulates it in MuJoCo, runs the arm's emulated
skin in virtual time and the daemon's core on its gateway lines
(:func:`cellbridge.skin_run.run_daemon_on_skin`), keeps the ground truth beside what the
daemon published, and prints the accuracy table. Deterministic for a seed; no processes,
ports or ptys. ``score`` scores files written by ``run --out`` (or a ``contact`` stream
recorded with ``cellbridge sub contact``) against a truth file; ``skin`` and ``mjcf`` print
the arm's skin description and MuJoCo model.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Any

from cellbridge.robot_score import Score, score

__all__ = ["add_arguments", "run", "run_scenario"]


def run_scenario(contacts: int, seed: int = 0, reporting: str = "periodic", idle: float = 0.0,
                 out: str | None = None, progress: bool = False) -> tuple[Score, dict[str, Any]]:
    """Simulate a scenario of ``contacts`` contacts (then ``idle`` s untouched), run the skin
    and the daemon's core in virtual time, and score; (score, figures of the run)."""
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
    from cellbridge.emulator.realtime.realtime import reporting_arg
    from cellbridge.emulator.world.robot_world import TimelineWorld, arm_skin, scenario, simulate
    from cellbridge.skin_run import T0, run_daemon_on_skin

    skin = arm_skin()
    presses = scenario(skin, contacts, seed)
    busy = max(p.end for p in presses) + 0.5
    seconds = busy + idle
    t0 = time.perf_counter()
    timeline = simulate(skin, presses, seconds)
    t_sim = time.perf_counter() - t0
    world = TimelineWorld(mesh_from_skin(skin), timeline)
    frames: list[tuple[float, list[dict[str, Any]]]] = []
    idle_ids: set[int] = set()
    t1 = time.perf_counter()
    shown = 0
    for t, topic, m in run_daemon_on_skin(skin, world, seconds, seed=seed,
                                          settings=Settings(reporting=reporting_arg(reporting))):
        if topic != "contact":
            continue
        ts = m["t_sample"] - T0 if m["t_sample"] is not None else t
        frames.append((ts, m["contacts"]))
        if ts > busy:
            idle_ids |= {c["id"] for c in m["contacts"] if c.get("missed", 0) == 0}
        if progress and int(t) > shown:
            shown = int(t)
            print(f"\r  virtual {t:6.1f} / {seconds:.1f} s", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    t_run = time.perf_counter() - t1
    truths = [tr.to_dict() for tr in timeline.truths]
    if out:
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, "truth.jsonl"), "w", encoding="utf-8") as fh:
            for d in truths:
                fh.write(json.dumps(d) + "\n")
        with open(os.path.join(out, "contacts.jsonl"), "w", encoding="utf-8") as fh:
            for ts, cs in frames:
                fh.write(json.dumps({"t": ts, "contacts": cs}, default=_plain) + "\n")
    sc = score(skin, truths, frames)
    figures = {"virtual_s": seconds, "simulate_s": t_sim, "skin_and_daemon_s": t_run, "idle_s": idle,
               "idle_false_contacts": len(idle_ids), "elements": skin.n, "gateways": len(skin.gateways)}
    return sc, figures


def _plain(v: Any) -> Any:
    return v.item() if hasattr(v, "item") else str(v)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "A simulated robot (MuJoCo) touches its emulated skin; the daemon's contacts are\n"
        "scored against what the simulation says touched it (needs the robot extra:\n"
        "pip install 'cellbridge[robot]').\n\n"
        "examples:\n"
        "  cellbridge robot run                    # 24 contacts, the accuracy table (a minute or two)\n"
        "  cellbridge robot run --contacts 200 --out run/   # keep truth.jsonl and contacts.jsonl\n"
        "  cellbridge robot score run/             # score them again\n"
        "  cellbridge robot skin > arm.toml        # the arm's skin: cellbridge mesh up arm.toml"
    )
    sub = parser.add_subparsers(dest="robot_command", metavar="ACTION", required=True)
    rn = sub.add_parser("run", help="simulate a scenario, run the skin and the daemon in virtual time, score")
    rn.add_argument("--contacts", type=int, default=24, help="contacts in the scenario, at least (default 24)")
    rn.add_argument("--seed", type=int, default=0, help="seed of the scenario and the skin (default 0)")
    rn.add_argument("--reporting", default="periodic", help="the bridges' reporting (default periodic; an event-based skin calibrates only as its heartbeats come)")
    rn.add_argument("--idle", type=float, default=0.0, help="seconds untouched after the scenario, where any contact is a false one (default 0)")
    rn.add_argument("--out", metavar="DIR", help="write DIR/truth.jsonl and DIR/contacts.jsonl")
    sc = sub.add_parser("score", help="score DIR/contacts.jsonl against DIR/truth.jsonl (from run --out)")
    sc.add_argument("dir")
    sub.add_parser("skin", help="print the arm's skin description (TOML)")
    sub.add_parser("mjcf", help="print the arm's MuJoCo model (MJCF)")


def run(args: argparse.Namespace) -> int:
    if args.robot_command == "skin":
        from cellbridge.emulator.world.robot_world import ARM_SKIN

        sys.stdout.write(ARM_SKIN)
        return 0
    if args.robot_command == "mjcf":
        from cellbridge.emulator.world.robot_world import arm_mjcf, arm_skin

        print(arm_mjcf(arm_skin()))
        return 0
    try:
        import mujoco  # type: ignore[import-untyped]  # noqa: F401  # only whether it is installed
    except ImportError:
        if args.robot_command == "run":
            print("cellbridge robot: needs MuJoCo: pip install 'cellbridge[robot]'", file=sys.stderr)
            return 2
    if args.robot_command == "score":
        from cellbridge.emulator.world.robot_world import arm_skin

        try:
            with open(os.path.join(args.dir, "truth.jsonl"), encoding="utf-8") as fh:
                truths = [json.loads(line) for line in fh if line.strip()]
            with open(os.path.join(args.dir, "contacts.jsonl"), encoding="utf-8") as fh:
                frames = [(d["t"], d["contacts"]) for d in (json.loads(line) for line in fh if line.strip())]
        except (OSError, ValueError, KeyError) as exc:
            print(f"cellbridge robot score: {args.dir}: {exc}", file=sys.stderr)
            return 2
        print(score(arm_skin(), truths, frames).table())
        return 0
    if args.contacts < 1:
        print("cellbridge robot run: --contacts must be >= 1", file=sys.stderr)
        return 2
    result, fig = run_scenario(args.contacts, args.seed, args.reporting, args.idle, args.out, progress=True)
    print(result.table())
    print(f"\n{fig['elements']} elements, {fig['gateways']} gateways; {fig['virtual_s']:.1f} s of virtual time: "
          f"MuJoCo {fig['simulate_s']:.1f} s, skin and daemon {fig['skin_and_daemon_s']:.1f} s"
          + (f"; idle {fig['idle_s']:.0f} s: {fig['idle_false_contacts']} false contacts" if fig["idle_s"] else ""))
    return 0 if math.isfinite(fig["virtual_s"]) else 1
