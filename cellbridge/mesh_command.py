"""``cellbridge mesh``: the emulator's mesh command (:mod:`cellbridge.emulator.realtime.mesh_cli`),
and its ``traffic`` action, which writes what the daemon reads (capture files, a daemon
configuration) and so lives above both layers.
"""

from __future__ import annotations

import argparse
import sys

from cellbridge.emulator.mesh.mesh import MeshError
from cellbridge.emulator.realtime import mesh_cli
from cellbridge.emulator.world.world import ScenarioError

add_arguments = mesh_cli.add_arguments


def run(args: argparse.Namespace) -> int:
    """``mesh traffic`` here, every other action in the emulator's command."""
    if args.mesh_command != "traffic":
        return mesh_cli.run(args)
    try:
        return _traffic(args)
    except (MeshError, ScenarioError) as exc:
        print(f"cellbridge mesh: {exc}", file=sys.stderr)
        return 2


def _traffic(args: argparse.Namespace) -> int:
    """A skin description's frame-level traffic into one capture per gateway, and a daemon
    configuration that replays them (emulator/mesh/skin_traffic.py)."""
    import json
    import os
    import time
    import tomllib

    from cellbridge.daemon.shell.capture import CaptureWriter
    from cellbridge.daemon.shell.skin_file import is_skin_file, load_skin
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.mesh import read_text
    from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
    from cellbridge.emulator.mesh.skin_traffic import SkinTraffic
    from cellbridge.emulator.world.world import World, check_on_skin, load_scenario
    from cellbridge.tactile.skin_geometry import SkinError

    text = read_text(args.skin, "skin description", MeshError)
    try:
        tomllib.loads(text)  # (a file that is no TOML is not "without [[patch]] tables")
    except tomllib.TOMLDecodeError as exc:
        raise MeshError(f"{args.skin}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise MeshError(f"{args.skin}: not valid TOML: nested too deeply") from None
    if not is_skin_file(text):
        raise MeshError(f"{args.skin}: not a skin description (no [[patch]] tables): 'mesh run' reads mesh files")
    try:
        skin = load_skin(args.skin)
    except SkinError as exc:
        raise MeshError(str(exc)) from None
    mesh = mesh_from_skin(skin, source=args.skin)
    contacts = load_scenario(args.scenario) if args.scenario else []
    for i, c in enumerate(contacts):
        check_on_skin(mesh, c, f"{args.scenario}: contact[{i}]")
    traffic = SkinTraffic(skin, World(mesh, contacts), settings=Settings(rate_hz=args.rate, reporting=args.reporting),
                          seed=args.seed)
    os.makedirs(args.out, exist_ok=True)
    writers = {g: CaptureWriter(os.path.join(args.out, f"gateway-{g}.cbcap")) for g in traffic.gateways}
    t0 = time.time()  # the recording's host times start now (a replay shifts them to its own start)
    c0 = time.process_time()
    try:
        for w in writers.values():  # an empty read at the start of each: a replay shifts each line to its
            w.write(t0, b"")  # own start, and this keeps the gateways' records of a frame as far apart as they came
        for t, g, data in traffic.run(args.seconds):
            writers[g].write(t0 + t, data)
    finally:
        for w in writers.values():
            w.close()
    cpu = time.process_time() - c0
    links = "".join(f'\n[[link]]\nname = "gateway-{g}"\nurl = "replay:gateway-{g}.cbcap"\n' for g in traffic.gateways)
    with open(os.path.join(args.out, "daemon.toml"), "w", encoding="utf-8") as fh:
        fh.write(f"# cellbridge daemon --config {os.path.join(args.out, 'daemon.toml')}: replays the gateways' lines\n"
                 f'[layout]\nfile = "{os.path.abspath(args.skin)}"\n{links}')
    print(json.dumps({"seconds": args.seconds, "elements": skin.n, "gateways": len(traffic.gateways),
                      "cpu_seconds": round(cpu, 3), **dict(traffic.counters)}, indent=1))
    return 0


