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
import os
import signal
import sys
import threading
import time
from typing import Any

from cellbridge.robot_files import RunFileError, prepare_out, read_run, write_run
from cellbridge.robot_score import Score, idle_false_ids, idle_line, score

__all__ = ["MAX_CONTACTS", "MAX_IDLE", "Stopped", "add_arguments", "run", "run_scenario", "truths_until"]


MAX_CONTACTS = 10_000  #: contacts in one run (each about 1 s of virtual time: hours of CPU already)
MAX_IDLE = 3600.0  #: s untouched after the scenario, at most


class Stopped(KeyboardInterrupt):
    """SIGTERM or Ctrl-C during a run: stops it (what was run is kept, said partial)."""


#: set by ``robot run``'s signal handler before it raises :class:`Stopped`: the run's loop
#: also stops on it, should the exception be lost on its way up (raised inside a destructor
#: or a callback whose caller drops what it raised)
STOP = threading.Event()


def run_scenario(contacts: int, seed: int = 0, reporting: str = "periodic", idle: float = 0.0,
                 out: str | None = None, progress: bool = False) -> tuple[Score, dict[str, Any]]:
    """Simulate a scenario of ``contacts`` contacts (then ``idle`` s untouched), run the skin
    and the daemon's core in virtual time, and score; (score, figures of the run).

    Ctrl-C (or :class:`Stopped`) ends the run early: the truths of what was run and the
    frames published so far are scored and written, marked partial (``figures["complete"]``
    false, ``run.json``'s ``complete`` false and ``until`` the last virtual second run)."""
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
    t1 = time.perf_counter()
    shown = 0
    until = 0.0
    complete = False
    try:
        for t, topic, m in run_daemon_on_skin(skin, world, seconds, seed=seed,
                                              settings=Settings(reporting=reporting_arg(reporting))):
            until = t
            if STOP.is_set():
                raise Stopped(0)
            if topic != "contact":
                continue
            ts = m["t_sample"] - T0 if m["t_sample"] is not None else t
            frames.append((ts, m["contacts"]))
            if progress and int(t) > shown:
                shown = int(t)
                print(f"\r  virtual {t:6.1f} / {seconds:.1f} s", end="", file=sys.stderr, flush=True)
        complete, until = True, seconds
    except KeyboardInterrupt:
        if progress:
            print(f"\n  stopped at virtual {until:.1f} of {seconds:.1f} s: what was run is scored, partial",
                  file=sys.stderr, end="")
    if progress:
        print(file=sys.stderr)
    t_run = time.perf_counter() - t1
    truths = [tr.to_dict() for tr in timeline.truths]
    meta = {"seed": seed, "contacts": contacts, "reporting": reporting, "idle": idle, "busy": busy,
            "virtual_s": seconds, "complete": complete, "until": until}
    if out:
        write_run(out, truths, frames, meta)
    scored, left = truths_until(truths, until) if not complete else (truths, 0)
    sc = score(skin, scored, frames)
    idle_run = max(0.0, min(until, seconds) - busy)
    figures = {"virtual_s": seconds, "simulate_s": t_sim, "skin_and_daemon_s": t_run, "idle_s": idle_run,
               "idle_false_contacts": len(idle_false_ids(frames, busy)), "elements": skin.n, "gateways": len(skin.gateways),
               "complete": complete, "until": until, "truths_left_out": left}
    return sc, figures


def truths_until(truths: list[dict[str, Any]], until: float) -> tuple[list[dict[str, Any]], int]:
    """The truths a partial run scores (those over before ``until``, with the release's
    margin), and how many it leaves out."""
    kept = [t for t in truths if t["end"] + 0.5 <= until]
    return kept, len(truths) - len(kept)


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
    rn = sub.add_parser("run", help="simulate a scenario, run the skin and the daemon in virtual time, score",
                        description="Simulate a scenario of --contacts presses on the arm's skin (MuJoCo), run "
                                    "its emulated skin and the daemon's core on them in virtual time, and print "
                                    "the daemon's contacts scored against the simulation's (a minute or two for "
                                    "24). Ctrl-C or SIGTERM stop it: the table of what ran is printed marked "
                                    "PARTIAL (exit status 130).")
    rn.add_argument("--contacts", type=int, default=24, help=f"contacts in the scenario, at least (1..{MAX_CONTACTS}; default 24)")
    rn.add_argument("--seed", type=int, default=0, help="seed of the scenario and the skin (default 0)")
    rn.add_argument("--reporting", default="periodic", help="the bridges' reporting (default periodic; an event-based skin calibrates only as its heartbeats come)")
    rn.add_argument("--idle", type=float, default=0.0, help=f"seconds untouched after the scenario, where any contact is a false one (0..{MAX_IDLE:.0f}; default 0)")
    rn.add_argument("--out", metavar="DIR", help="write DIR/truth.jsonl, DIR/contacts.jsonl and DIR/run.json "
                    "(made and checked before the run; a stopped run's files say partial); a DIR holding "
                    "an earlier run's is refused")
    rn.add_argument("--force", action="store_true", help="with --out: replace the earlier run's files in DIR")
    sc = sub.add_parser("score", help="score DIR/contacts.jsonl against DIR/truth.jsonl (from run --out)",
                        description="Score the contacts of DIR/contacts.jsonl (written by 'robot run --out DIR', "
                                    "or a 'cellbridge sub contact' recording) against the true contacts of "
                                    "DIR/truth.jsonl, and print the table. Files of two runs, and lines it cannot "
                                    "score, are refused, naming the file and line.")
    sc.add_argument("dir")
    sub.add_parser("skin", help="print the arm's skin description (TOML)",
                   description="Print the skin description (TOML) of the arm 'robot run' presses on: its patches "
                               "of elements on the torso, upper arm and forearm ('cellbridge mesh up' runs it).")
    sub.add_parser("mjcf", help="print the arm's MuJoCo model (MJCF)",
                   description="Print the MuJoCo model (MJCF XML) of the arm 'robot run' simulates.")


def _score_dir(directory: str) -> int:
    """``robot score DIR``: the table, or a message naming the file and line it could not use."""
    from cellbridge.emulator.world.robot_world import arm_skin

    try:
        got = read_run(directory)
        got.check_on(arm_skin())
    except RunFileError as exc:
        print(f"cellbridge robot score: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"cellbridge robot score: {exc.filename or directory}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    truths = got.truths
    if got.meta.get("complete") is False:
        until = float(got.meta.get("until") or 0.0)
        truths, left = truths_until(truths, until)
        got.notes.append(f"a partial run (stopped at virtual {until:.1f} s): {left} true contacts after it "
                         "left out")
        if not truths:
            print(f"cellbridge robot score: {directory}: a partial run with no true contact over before it "
                  f"stopped (virtual {until:.1f} s): nothing to score", file=sys.stderr)
            return 2
    print(score(arm_skin(), truths, got.frames).table())
    busy, end = got.meta.get("busy"), got.meta.get("until")  # run.json's: finite numbers when there
    if isinstance(busy, (int, float)) and isinstance(end, (int, float)) and end > busy:
        print(idle_line(len(idle_false_ids(got.frames, busy)), end - busy))
    for note in got.notes:
        print(f"note: {note}")
    return 0


def _run_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with ``robot run``'s options, found before an hour's run, or None."""
    from cellbridge.emulator.realtime.realtime import reporting_arg

    if not 1 <= args.contacts <= MAX_CONTACTS:
        return f"--contacts must be within 1..{MAX_CONTACTS}, got {args.contacts}"
    if not 0.0 <= args.idle <= MAX_IDLE:  # False for NaN
        return f"--idle must be within 0..{MAX_IDLE:.0f} s, got {args.idle}"
    try:
        reporting_arg(args.reporting)
    except argparse.ArgumentTypeError as exc:
        return f"--reporting: {exc}"
    if args.force and args.out is None:
        return "--force replaces an earlier run's files in --out DIR: it goes with --out"
    if args.out is not None:
        try:
            prepare_out(args.out, force=args.force)
        except RunFileError as exc:
            return str(exc)
    return None


def _stop(signum: int, _frame: Any) -> None:
    STOP.set()
    raise Stopped(signum)


def run(args: argparse.Namespace) -> int:
    try:
        status = _run(args)
        sys.stdout.flush()
        return status
    except BrokenPipeError:  # the reader went away (| head): the end of the output, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _run(args: argparse.Namespace) -> int:
    if args.robot_command == "skin":
        from cellbridge.emulator.world.robot_world import ARM_SKIN

        sys.stdout.write(ARM_SKIN)
        return 0
    if args.robot_command == "mjcf":
        from cellbridge.emulator.world.robot_world import arm_mjcf, arm_skin

        print(arm_mjcf(arm_skin()))
        return 0
    if args.robot_command == "score":
        return _score_dir(args.dir)
    try:
        import mujoco  # type: ignore[import-untyped]  # noqa: F401  # only whether it is installed
    except ImportError:
        print("cellbridge robot run: needs MuJoCo: pip install 'cellbridge[robot]'", file=sys.stderr)
        return 2
    problem = _run_problem(args)
    if problem:
        print(f"cellbridge robot run: {problem}", file=sys.stderr)
        return 2
    STOP.clear()
    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        result, fig = run_scenario(args.contacts, args.seed, args.reporting, args.idle, args.out, progress=True)
    except KeyboardInterrupt:  # a second Ctrl-C or SIGTERM, while scoring or writing
        print("cellbridge robot run: stopped" + (f"; nothing of this run kept in {args.out}" if args.out else ""),
              file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"cellbridge robot run: cannot write {exc.filename or args.out}: {exc.strerror or exc}; "
              "nothing of this run kept", file=sys.stderr)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if not fig["complete"]:
        print(f"PARTIAL: stopped at virtual {fig['until']:.1f} of {fig['virtual_s']:.1f} s; "
              f"{fig['truths_left_out']} true contacts after it left out"
              + (f"; {args.out}/run.json says complete: false" if args.out else ""))
    print(result.table())
    print(f"\n{fig['elements']} elements, {fig['gateways']} gateways; {fig['virtual_s']:.1f} s of virtual time: "
          f"MuJoCo {fig['simulate_s']:.1f} s, skin and daemon {fig['skin_and_daemon_s']:.1f} s"
          + (f"; {idle_line(fig['idle_false_contacts'], fig['idle_s'])}" if fig["idle_s"] else ""))
    return 0 if fig["complete"] else 130
