"""Reading the skin layout file the daemon's ``[layout] file`` names (the file I/O the
tactile layer leaves out: :func:`cellbridge.tactile.parse_layout` takes text)."""

from __future__ import annotations

from os import PathLike

from cellbridge.daemon.shell.skin_file import is_skin_file, load_skin, read_bounded
from cellbridge.tactile.layout import SkinLayout, parse_layout
from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["load_layout", "load_layout_file"]


def load_layout_file(path: str | PathLike[str]) -> tuple[SkinLayout, SkinGeometry | None]:
    """Read a skin layout TOML file (format: :func:`cellbridge.tactile.parse_layout`), or a
    skin description (``[[patch]]`` tables, :mod:`cellbridge.daemon.shell.skin_file`): the
    layout, and the description when it is one. The daemon needs both: the layout is its
    atlas, the description puts each contact on its link and in ``topology`` (with the
    layout alone, a contact on a robot's skin read as a point of one flat plane).

    Every problem, a missing file included, is a ``ValueError`` naming the file.
    """
    text = read_bounded(path, "layout")
    if is_skin_file(text):
        skin = load_skin(path)
        return skin.layout(), skin
    return parse_layout(text, source=str(path)), None


def load_layout(path: str | PathLike[str]) -> SkinLayout:
    """The layout of :func:`load_layout_file` (a skin description's: its atlas)."""
    return load_layout_file(path)[0]
