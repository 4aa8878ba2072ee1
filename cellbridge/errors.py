"""The root of the errors cellbridge raises on purpose.

Each layer raises its own kind (:class:`~cellbridge.protocol.ProtocolError`,
``ConfigError``, ``MeshError`` ...), each a :class:`CellbridgeError` and a ``ValueError``
(bad input, as before), so a tool embedding several layers catches them all with one
``except CellbridgeError`` and still tells them apart. A leaf module like ``_version``:
every layer may import it.
"""

from __future__ import annotations


class CellbridgeError(Exception):
    """Something cellbridge refused, with a message that says what and where."""


__all__ = ["CellbridgeError"]
