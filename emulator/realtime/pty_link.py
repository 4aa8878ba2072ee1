"""A stable name for a gateway's pseudo-terminal: ``DIR/gateway-<id>``, a symlink to ``/dev/pts/N``.

The pty's number changes each time the mesh starts; a daemon configured with the
symlink finds the new one on its next reconnect, as it finds a re-plugged board
through ``/dev/serial/by-id/``.
"""

from __future__ import annotations

import os
from pathlib import Path


def link_gateway(directory: str | Path, gateway: int, device: str) -> Path:
    """Point ``directory/gateway-<gateway>`` at ``device``, replacing an older link in one
    step (a reader never finds it missing); returns the link's path."""
    link = Path(directory) / f"gateway-{gateway}"
    tmp = link.with_name(f".{link.name}.{os.getpid()}")
    tmp.unlink(missing_ok=True)
    os.symlink(device, tmp)
    os.replace(tmp, link)
    return link


def link_folder_problem(directory: str | Path) -> str | None:
    """Make ``directory`` (and its parents) for the links, before anything starts; a sentence
    saying why it cannot hold them, or None."""
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as exc:
        return f"--pty-link {directory}: cannot make it: {exc.strerror or exc}"
    if not os.access(directory, os.W_OK | os.X_OK):
        return f"--pty-link {directory}: cannot write in it"
    return None
