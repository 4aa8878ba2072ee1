"""``cellbridge mesh``: generate and check mesh files, and bring an emulated skin up."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from cellbridge.emulator.mesh.mesh import Mesh, MeshError, load_mesh, mesh_to_toml
from cellbridge.emulator.mesh.meshgen import generate
from cellbridge.emulator.mesh.readout_load import FITS_BELOW, CellLoad, load_line, load_warning, readout_load
from cellbridge.emulator.realtime.realtime import REPORTING_HELP, rate_arg, reporting_arg, seconds_arg
from cellbridge.emulator.world.world import ScenarioError


def _run_virtual(args: argparse.Namespace) -> int:
    import json

    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.virtual import VirtualMesh
    from cellbridge.emulator.world.world import World, check_on_skin, load_scenario

    mesh = load_mesh(args.mesh)
    contacts = load_scenario(args.scenario) if args.scenario else []
    for i, c in enumerate(contacts):
        check_on_skin(mesh, c, f"{args.scenario}: contact[{i}]")
    if args.capture:  # made before the run: a folder that cannot be is said at once, not after it
        _write(args.capture, None)
    world = World(mesh, contacts)
    vm = VirtualMesh(mesh, seed=args.seed, world=world, settings=Settings(rate_hz=args.rate, reporting=args.reporting))
    result = vm.run(args.seconds)
    if args.capture:
        for g, data in vm.serial.items():
            _write(os.path.join(args.capture, f"gateway-{g}.bin"), data)
    samples = result.samples()
    print(json.dumps({
        "seconds": result.seconds,
        "samples_delivered": {str(b): len(samples.get(b, [])) for b in mesh.ids},
        "cut_off": result.cut_off,
        "parents": {str(b): p for b, p in result.parents.items()},
        "medium": result.medium,
        "counters": {str(b): c for b, c in result.counters.items()},
    }, indent=1))
    return 0


def _write(path: str, data: bytes | bytearray | str | None) -> None:
    """Write ``data`` to the file ``path`` (``None``: make the folder ``path``). One that cannot
    be made (no such folder, a file where the folder goes, no permission) is a
    :class:`MeshError` naming it: the user reads a sentence, not a traceback."""
    try:
        if data is None:
            os.makedirs(path, exist_ok=True)
            return
        with open(path, "wb") as fh:
            fh.write(data.encode("utf-8") if isinstance(data, str) else data)
    except OSError as exc:
        raise MeshError(f"{path}: cannot write: {exc.strerror or exc}") from None


def warn_if_not_fitting(mesh: Mesh, rate: int, acked: bool = True) -> CellLoad:
    """Print :func:`~cellbridge.emulator.mesh.readout_load.load_warning` on standard error
    when ``mesh`` cannot carry its readout at ``rate`` Hz (``mesh check``, ``mesh run`` and
    ``mesh up``, before they start; ``acked``: its records are acknowledged hop by hop, as
    in virtual time; the real-time shells send them once). Returns the load."""
    load = readout_load(mesh, rate, acked)
    if not load.fits:
        print(load_warning(load), file=sys.stderr, flush=True)
    return load


def _ids(text: str) -> list[int]:
    try:
        return [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated bridge ids, got {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Mesh files describe an emulated skin: cells, bridges (their cells, element\n"
        "position, gateway flag) and link loss / bit-error rates.\n\n"
        "examples:\n"
        "  cellbridge mesh gen line 8 -o line8.toml        # 8 bridges, 7 hops, gateway 1\n"
        "  cellbridge mesh gen grid 4 4 -o grid4.toml      # 16 bridges, gateway 6 (the centre)\n"
        "  cellbridge mesh gen grid 4 4 --gateways 1,16    # two gateways, to stdout\n"
        "  cellbridge mesh gen random 32 --seed 7 --loss 0.01\n"
        "  cellbridge mesh check line8.toml\n"
        "  cellbridge mesh run line8.toml --seconds 5 --scenario presses.toml --capture out/\n"
        "  cellbridge mesh up line8.toml                   # one process per bridge\n"
        "  cellbridge mesh traffic humanoid.toml --seconds 120 --scenario presses.toml --out run/\n"
        "                                                  # a skin description's gateway lines, frame level\n"
        "  cellbridge mesh up grid8.toml --reporting event:40:1000   # idle elements: heartbeats only"
    )
    sub = parser.add_subparsers(dest="mesh_command", metavar="ACTION", required=True)
    gen = sub.add_parser("gen", help="write a generated mesh file (line N | ring N | grid R C | random N)",
                         description="Write a mesh file of a generated shape: a line or ring of N bridges, a "
                                     "grid of R x C, or a random mesh of N; on standard output, or into the "
                                     "file -o names (replaced if it exists).")
    gen.add_argument("kind", choices=["line", "ring", "grid", "random"])
    gen.add_argument("size", type=int, nargs="+", help="N, or R C for a grid")
    gen.add_argument("--gateways", type=_ids, default=None,
                     help="gateway bridge ids, comma-separated (default: a grid's centre bridge, the shallowest "
                          "routing tree, e.g. 6 of a 4x4; bridge 1 of the other kinds)")
    gen.add_argument("--loss", type=float, default=0.0, help="frame loss probability per delivery (default 0)")
    gen.add_argument("--ber", type=float, default=0.0, help="bit-error rate per delivered bit (default 0)")
    gen.add_argument("--side", type=float, default=0.040, help="element side and pitch in metres (default 0.04)")
    gen.add_argument("--seed", type=int, default=None, help="random mesh only: seed of the shape (default 0)")
    gen.add_argument("-o", "--output", help="file to write (default: standard output)")
    chk = sub.add_parser("check", help="validate a mesh file and summarise it, with the share of its busiest "
                                       "cell's airtime the readout takes",
                         description="Validate a mesh file and print a line of what it holds (bridges, cells, "
                                     "gateways) and one of the readout's load on its busiest cell at --rate; "
                                     "a load that does not fit is warned of on standard error. Exit status 2 "
                                     "and a sentence naming the problem for a bad file.")
    chk.add_argument("mesh", help="a mesh file (TOML: cellbridge mesh gen writes one; docs/emulator.md)")
    chk.add_argument("--rate", type=rate_arg, default=100,
                     help="sampling rate in Hz, 1..250, whose readout load to report (default 100); above "
                          f"{FITS_BELOW * 100:.0f}%% of a cell's airtime a warning says the readout does not fit")
    rn = sub.add_parser("run", help="run a mesh in virtual time (faster than real time, deterministic)",
                        description="Run a mesh in virtual time, in this one process (faster than real time; "
                                    "the same seed gives the same run), and print its counters as JSON: samples "
                                    "delivered per bridge, bridges cut off, each one's parent, the medium's and "
                                    "each bridge's counters. --capture keeps each gateway's serial line.")
    rn.add_argument("mesh", help="a mesh file (TOML: cellbridge mesh gen writes one; docs/emulator.md)")
    rn.add_argument("--seconds", type=seconds_arg, default=5.0, help="virtual seconds to run (default 5)")
    rn.add_argument("--scenario", help="TOML file of [[contact]] stimuli")
    rn.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    rn.add_argument("--rate", type=rate_arg, default=100, help="sampling rate in Hz, 1..250 (default 100)")
    rn.add_argument("--reporting", type=reporting_arg, default="periodic", metavar="MODE", help=REPORTING_HELP)
    rn.add_argument("--capture", metavar="DIR",
                    help="write each gateway's serial stream to DIR/gateway-<id>.bin (read it with cellbridge decode)")
    tr = sub.add_parser("traffic", help="a skin description's gateway lines at frame level (the readout records, "
                                        "no cells): captures the daemon replays",
                        description="Write what the gateways of a skin description (TOML with [[patch]] tables) "
                                    "send on their serial lines, at frame level: DIR/gateway-<id>.cbcap per "
                                    "gateway and DIR/daemon.toml, with which 'cellbridge daemon --config "
                                    "DIR/daemon.toml' replays them in real time. Prints the run's counters as "
                                    "JSON.")
    tr.add_argument("skin", help="a skin description (TOML with [[patch]] tables)")
    tr.add_argument("--seconds", type=seconds_arg, default=10.0, help="virtual seconds (default 10)")
    tr.add_argument("--scenario", help="TOML file of [[contact]] stimuli (atlas positions)")
    tr.add_argument("--seed", type=int, default=0, help="seed of the readings' noise (default 0)")
    tr.add_argument("--rate", type=rate_arg, default=100, help="sampling rate in Hz, 1..250 (default 100)")
    tr.add_argument("--reporting", type=reporting_arg, default="periodic", metavar="MODE", help=REPORTING_HELP)
    tr.add_argument("--out", metavar="DIR", required=True,
                    help="write DIR/gateway-<id>.cbcap (one per gateway) and DIR/daemon.toml (replays them)")
    up = sub.add_parser("up", help="start the medium, the world and one process per bridge (real time)",
                        description="Start an emulated skin in real time: the medium, the world and one process "
                                    "per bridge. Prints a line 'gateway <id> <device>' per gateway, its "
                                    "pseudo-terminal, which the daemon opens as it would /dev/ttyUSB0 (with --tcp "
                                    "also socket://127.0.0.1:PORT); 'cellbridge press' presses on it. Runs until "
                                    "Ctrl-C or SIGTERM, which stop every process it started; a process that dies "
                                    "meanwhile is reported and the others keep running.")
    up.add_argument("mesh", help="a mesh file (TOML: cellbridge mesh gen writes one; docs/emulator.md)")
    try:
        importlib.import_module("cellbridge.emulator.realtime.process_up").add_arguments(up)
    except ImportError:  # the process shells are optional for generating files
        pass


def run(args: argparse.Namespace) -> int:
    try:
        if args.mesh_command == "gen":
            if args.seed is not None and args.kind != "random":  # a line, ring or grid has one shape: a seed changes nothing
                raise MeshError(f"--seed shapes a random mesh only, not a {args.kind}")
            kw = {} if args.gateways is None else {"gateways": args.gateways}
            mesh = generate(args.kind, args.size, loss=args.loss, ber=args.ber, side=args.side,
                            seed=args.seed or 0, **kw)
            text = mesh_to_toml(mesh)
            if args.output:
                _write(args.output, text)
            else:
                sys.stdout.write(text)
            return 0
        if args.mesh_command == "check":
            mesh = load_mesh(args.mesh)
            sizes = [len(v) for v in mesh.members().values()]
            print(f"{args.mesh}: ok: {len(mesh.bridges)} bridges, {len(mesh.cells)} cells "
                  f"(up to {max(sizes)} bridges on one), gateways {', '.join(map(str, mesh.gateways))}")
            print(load_line(warn_if_not_fitting(mesh, args.rate)))
            return 0
        if args.mesh_command == "run":
            warn_if_not_fitting(load_mesh(args.mesh), args.rate)
            return _run_virtual(args)
        if args.mesh_command == "traffic":  # cellbridge/mesh_command.py runs it (it writes daemon captures)
            raise MeshError("'mesh traffic' runs through the cellbridge command (cellbridge mesh traffic)")
        return int(importlib.import_module("cellbridge.emulator.realtime.process_up").run(args) or 0)
    except (MeshError, ScenarioError) as exc:
        print(f"cellbridge mesh: {exc}", file=sys.stderr)
        return 2
