"""``cellbridge mesh``: generate and check mesh files, and bring an emulated skin up."""

from __future__ import annotations

import argparse
import importlib
import sys

from cellbridge.emulator.mesh import MeshError, load_mesh, mesh_to_toml
from cellbridge.emulator.meshgen import generate


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
        "  cellbridge mesh gen grid 4 4 --gateways 1,16    # two gateways, to stdout\n"
        "  cellbridge mesh gen random 32 --seed 7 --loss 0.01\n"
        "  cellbridge mesh check line8.toml\n"
        "  cellbridge mesh up line8.toml                   # one process per bridge"
    )
    sub = parser.add_subparsers(dest="mesh_command", metavar="ACTION", required=True)
    gen = sub.add_parser("gen", help="write a generated mesh file (line N | ring N | grid R C | random N)")
    gen.add_argument("kind", choices=["line", "ring", "grid", "random"])
    gen.add_argument("size", type=int, nargs="+", help="N, or R C for a grid")
    gen.add_argument("--gateways", type=_ids, default=[1], help="gateway bridge ids, comma-separated (default 1)")
    gen.add_argument("--loss", type=float, default=0.0, help="frame loss probability per delivery (default 0)")
    gen.add_argument("--ber", type=float, default=0.0, help="bit-error rate per delivered bit (default 0)")
    gen.add_argument("--side", type=float, default=0.040, help="element side and pitch in metres (default 0.04)")
    gen.add_argument("--seed", type=int, default=0, help="random mesh only: seed of the shape (default 0)")
    gen.add_argument("-o", "--output", help="file to write (default: standard output)")
    chk = sub.add_parser("check", help="validate a mesh file and summarise it")
    chk.add_argument("mesh")
    up = sub.add_parser("up", help="start the medium, the world and one process per bridge (real time)")
    up.add_argument("mesh")
    try:
        importlib.import_module("cellbridge.emulator.process_up").add_arguments(up)
    except ImportError:  # the process shells are optional for generating files
        pass


def run(args: argparse.Namespace) -> int:
    try:
        if args.mesh_command == "gen":
            mesh = generate(args.kind, args.size, gateways=args.gateways, loss=args.loss,
                            ber=args.ber, side=args.side, seed=args.seed)
            text = mesh_to_toml(mesh)
            if args.output:
                with open(args.output, "w", encoding="utf-8") as fh:
                    fh.write(text)
            else:
                sys.stdout.write(text)
            return 0
        if args.mesh_command == "check":
            mesh = load_mesh(args.mesh)
            sizes = [len(v) for v in mesh.members().values()]
            print(f"{args.mesh}: ok: {len(mesh.bridges)} bridges, {len(mesh.cells)} cells "
                  f"(up to {max(sizes)} bridges on one), gateways {', '.join(map(str, mesh.gateways))}")
            return 0
        return int(importlib.import_module("cellbridge.emulator.process_up").run(args) or 0)
    except MeshError as exc:
        print(f"cellbridge mesh: {exc}", file=sys.stderr)
        return 2
