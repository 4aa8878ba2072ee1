"""Hand-made wire bytes for the protocol tests (shared, so every test seals alike).

A test that builds or corrupts a frame by hand wants its bytes to get past the CRC to
the checks behind it (header, fragment and msgpack parsers): :func:`sealed` appends the
CRC-16 the way docs/protocol.md §2 says, big-endian after the body.
"""

from __future__ import annotations

from cellbridge.protocol import crc16


def sealed(body: bytes) -> bytes:
    """``body`` followed by its CRC-16 (big-endian): a frame, or a datagram's bytes, with a correct checksum."""
    return body + crc16(body).to_bytes(2, "big")
