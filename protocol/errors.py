"""The one exception the protocol layer raises for bad input.

Every decoder in :mod:`cellbridge.protocol` turns any malformed input into a
:class:`ProtocolError` (or a counted drop), so a long-running daemon can catch a
single type and keep going. ``cause`` is a short stable key, used as the name of
the drop counter the error is tallied under.
"""

from __future__ import annotations

from cellbridge.errors import CellbridgeError


class ProtocolError(CellbridgeError, ValueError):
    """Malformed, unsupported or inconsistent wire data."""

    def __init__(self, cause: str, detail: str = "") -> None:
        self.cause = cause
        self.detail = detail
        super().__init__(f"{cause}: {detail}" if detail else cause)
