"""Reading the skin layout file the daemon's ``[layout] file`` names (the file I/O the
tactile layer leaves out: :func:`cellbridge.tactile.parse_layout` takes text)."""

from __future__ import annotations

from os import PathLike

from cellbridge.daemon.shell.skin_file import is_skin_file, load_skin
from cellbridge.tactile.layout import SkinLayout, parse_layout


def load_layout(path: str | PathLike[str]) -> SkinLayout:
    """Read a skin layout TOML file (format: :func:`cellbridge.tactile.parse_layout`), or a
    skin description (``[[patch]]`` tables: its atlas, :mod:`cellbridge.daemon.shell.skin_file`).

    Every problem, a missing file included, is a ``ValueError`` naming the file.
    """
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read layout: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: layout is not UTF-8 text") from None
    if is_skin_file(text):
        return load_skin(path).layout()
    return parse_layout(text, source=str(path))
