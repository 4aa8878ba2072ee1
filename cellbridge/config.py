"""Loading the files a user hands to cellbridge (the file I/O the pure layers leave out).

The layout file is read by the daemon's own loader; it is offered here for tools."""

from __future__ import annotations

from cellbridge.daemon.shell.layout_file import load_layout

__all__ = ["load_layout"]
