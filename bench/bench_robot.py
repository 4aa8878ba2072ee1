"""Contacts on a robot against ground truth: a scripted MuJoCo scenario on the arm's skin.

Prints the accuracy table; asserts nothing. Run: ``.venv/bin/python bench/bench_robot.py
[--contacts 200] [--idle 60] [--idle-frames 600]``. The scenario (``cellbridge robot run``): single presses
anywhere on the torso's planes and the arm's cylinders, presses across wrap seams and
across the seam of two patches of one link, slides, two presses at once; the arm swings
throughout. MuJoCo resolves the contacts, the emulated skin (45 elements, 3 gateways,
virtual time, periodic 100 Hz) reads them, the daemon's core estimates them. Needs the
robot extra (mujoco). Long: on two busy cores, about 3-8 s of CPU per virtual second.

False contacts while idle are counted twice: in ``--idle`` s after the scenario on the
cycle-level mesh (the cells, their losses; costly), and in ``--idle-frames`` s of the same
skin untouched on the frame-level generator (:class:`cellbridge.emulator.mesh.skin_traffic.SkinTraffic`:
the firmware's own records and element noise, without the cells), which reaches the
ten minutes of the target at a fraction of the cost. A false contact is an id the daemon
published with every element known.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout too

from cellbridge.robot import run_scenario
from cellbridge.robot_score import idle_line


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--contacts", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--idle", type=float, default=60.0, help="untouched seconds after the scenario (cycle-level)")
    ap.add_argument("--idle-frames", type=float, default=600.0,
                    help="untouched seconds on the frame-level generator (0: none)")
    ap.add_argument("--out", help="keep truth.jsonl and contacts.jsonl here")
    a = ap.parse_args()
    try:
        import mujoco  # type: ignore[import-untyped]  # noqa: F401  # no type information published
    except ImportError:
        print("bench_robot: needs mujoco (pip install 'cellbridge[robot]'); skipped")
        return 0
    score, fig = run_scenario(a.contacts, a.seed, "periodic", a.idle, a.out, progress=True)
    print(score.table())
    print(f"after the scenario: {idle_line(fig['idle_false_contacts'], fig['idle_s'])}")
    print(f"{fig['elements']} elements, {fig['gateways']} gateways; {fig['virtual_s']:.1f} s of virtual time: "
          f"MuJoCo {fig['simulate_s']:.1f} s, skin and daemon {fig['skin_and_daemon_s']:.1f} s")
    if a.idle_frames > 0:
        ids, reports, cpu = idle_frame_level(a.idle_frames, a.seed)
        print(f"on the frame-level generator: {idle_line(ids, a.idle_frames)}, in {reports} contact messages; "
              f"{cpu:.0f} s of CPU")
    return 0


def idle_frame_level(seconds: float, seed: int) -> tuple[int, int, float]:
    """(false contact ids, contact messages, CPU s) of the arm's skin untouched for
    ``seconds``, read by the daemon's core from the frame-level generator."""
    import time

    from cellbridge.emulator.mesh.skin_traffic import SkinTraffic
    from cellbridge.emulator.world.robot_world import arm_skin

    from cellbridge.skin_run import run_daemon_on_traffic

    c0 = time.process_time()
    ids: set[int] = set()
    reports = 0
    for _t, topic, m in run_daemon_on_traffic(SkinTraffic(arm_skin(), seed=seed), seconds):
        if topic == "contact":
            reports += 1
            ids |= {c["id"] for c in m["contacts"] if c.get("missed", 0) == 0}
    return len(ids), reports, time.process_time() - c0


if __name__ == "__main__":
    raise SystemExit(main())
