"""Contacts on a robot against ground truth: a scripted MuJoCo scenario on the arm's skin.

Prints the accuracy table; asserts nothing. Run: ``.venv/bin/python bench/bench_robot.py
[--contacts 200] [--idle 600]``. The scenario (``cellbridge robot run``): single presses
anywhere on the torso's planes and the arm's cylinders, presses across wrap seams and
across the seam of two patches of one link, slides, two presses at once; the arm swings
throughout. MuJoCo resolves the contacts, the emulated skin (45 elements, 3 gateways,
virtual time, periodic 100 Hz) reads them, the daemon's core estimates them. Needs the
robot extra (mujoco). Long: on two busy cores, about 8 s of CPU per virtual second.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout too

from cellbridge.robot import run_scenario  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--contacts", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--idle", type=float, default=60.0, help="untouched seconds after the scenario")
    ap.add_argument("--out", help="keep truth.jsonl and contacts.jsonl here")
    a = ap.parse_args()
    try:
        import mujoco  # noqa: F401
    except ImportError:
        print("bench_robot: needs mujoco (pip install 'cellbridge[robot]'); skipped")
        return 0
    score, fig = run_scenario(a.contacts, a.seed, "periodic", a.idle, a.out, progress=True)
    print(score.table())
    print(f"idle {fig['idle_s']:.0f} s after the scenario: {fig['idle_false_contacts']} false contacts "
          f"(target: at most 1 per 10 minutes)")
    print(f"{fig['elements']} elements, {fig['gateways']} gateways; {fig['virtual_s']:.1f} s of virtual time: "
          f"MuJoCo {fig['simulate_s']:.1f} s, skin and daemon {fig['skin_and_daemon_s']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
