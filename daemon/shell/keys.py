"""``cellbridge keys gen``: CURVE key pairs for the daemon and its remote clients.

The files are ZeroMQ's certificate format (the one czmq and pyzmq's
``zmq.auth.load_certificate`` read): ``NAME.key`` holds the public key and may be
copied anywhere; ``NAME.key_secret`` holds both keys and is created 0600 from the
start (never world-readable, not even for an instant).
"""

from __future__ import annotations

import argparse
import os
import sys
from datetime import UTC, datetime
from pathlib import Path

import zmq
from zmq.auth import load_certificate

_BANNER = "#   ZeroMQ CURVE {kind} certificate, written by `cellbridge keys gen` on {when}\n"
_PUBLIC_NOTE = "#   Public: copy it to the peers that must know this key.\n\n"
_SECRET_NOTE = "#   SECRET: keep it on this host, readable by its owner only.\n\n"


def write_keypair(directory: Path, name: str, *, force: bool = False) -> tuple[Path, Path]:
    """Write ``NAME.key`` (0644) and ``NAME.key_secret`` (0600) into ``directory``.

    Refuses (FileExistsError) to replace an existing pair unless ``force``: a
    lost secret key locks its clients out. ValueError for a name that is not a
    plain file name.
    """
    if not name or name in (".", "..") or "/" in name or "\0" in name:
        raise ValueError(f"key name must be a plain file name, got {name!r}")
    public_path, secret_path = directory / f"{name}.key", directory / f"{name}.key_secret"
    if not force:
        for path in (public_path, secret_path):
            if path.exists():
                raise FileExistsError(f"{path} exists (use --force to replace the pair)")
    public, secret = (k.decode("ascii") for k in zmq.curve_keypair())
    when = datetime.now(UTC).isoformat(timespec="seconds")
    curve = f'curve\n    public-key = "{public}"\n'
    _write_atomic(secret_path, _BANNER.format(kind="Secret", when=when) + _SECRET_NOTE + "metadata\n"
                  + curve + f'    secret-key = "{secret}"\n', 0o600)
    _write_atomic(public_path, _BANNER.format(kind="Public", when=when) + _PUBLIC_NOTE + "metadata\n"
                  + curve, 0o644)
    return public_path, secret_path


def make_key_dir(directory: Path) -> list[Path]:
    """Make ``directory`` and its missing parents, each 0700 whatever the umask (a folder
    of secret keys is its owner's alone; one that is there keeps its mode). The folders
    made, outermost first. OSError when one cannot be made."""
    missing: list[Path] = []
    d = directory
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    made: list[Path] = []
    for d in reversed(missing):
        try:
            d.mkdir(mode=0o700)
        except FileExistsError:  # made meanwhile by another: its mode is its maker's
            continue
        os.chmod(d, 0o700)
        made.append(d)
    return made


def _write_atomic(path: Path, text: str, mode: int) -> None:
    """Create a temporary file with ``mode`` already set, then rename it into place."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, mode & 0o600)
    try:
        with os.fdopen(fd, "w", encoding="ascii") as fh:
            fh.write(text)
            os.fchmod(fh.fileno(), mode)  # exact mode, whatever the umask
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Manage ZeroMQ CURVE keys. The daemon binds beyond loopback only with CURVE, and\n"
        "then serves only clients whose public key file lies in its allowed_clients_dir.\n\n"
        "examples:\n"
        "  cellbridge keys gen --dir /etc/cellbridge server       # the daemon's pair\n"
        "  cellbridge keys gen robot-arm                          # a client's pair, here\n"
        "  cp robot-arm.key /etc/cellbridge/clients/              # allow that client\n"
        "then in /etc/cellbridge/daemon.toml:\n"
        "  [security]\n"
        '  server_secret_file = "/etc/cellbridge/server.key_secret"\n'
        '  allowed_clients_dir = "/etc/cellbridge/clients"'
    )
    actions = parser.add_subparsers(dest="keys_action", metavar="ACTION", required=True)
    gen = actions.add_parser("gen", help="write a new key pair: NAME.key (public) and NAME.key_secret (0600)",
                             description="Write a new CURVE key pair: NAME.key (public, 0644) and "
                                         "NAME.key_secret (public and secret key, 0600).")
    gen.add_argument("name", nargs="?", default="server",
                     help="base name of the two files (default: server)")
    gen.add_argument("--dir", type=Path, default=Path("."),
                     help="directory to write into (default: .); made if missing, with its missing parents, "
                          "mode 0700 (a folder that is there keeps its mode)")
    gen.add_argument("--force", action="store_true", help="replace an existing pair of that name")


def run(args: argparse.Namespace) -> int:
    try:
        made = make_key_dir(args.dir)
    except OSError as exc:
        print(f"cellbridge keys gen: --dir {args.dir}: cannot make it: {exc.strerror or exc}", file=sys.stderr)
        return 2
    for d in made:
        print(f"made {d}  (mode 0700)")
    try:
        public_path, secret_path = write_keypair(args.dir, args.name, force=args.force)
    except (ValueError, FileExistsError) as exc:
        print(f"cellbridge keys gen: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"cellbridge keys gen: cannot write into {args.dir}: {exc.strerror}", file=sys.stderr)
        return 2
    public = load_certificate(public_path)[0].decode()
    print(f"public key  {public_path}  (Z85 {public})")
    print(f"secret key  {secret_path}  (mode 0600: keep it private)")
    return 0
