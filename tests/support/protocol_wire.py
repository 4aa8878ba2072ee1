"""Hand-made wire bytes for the protocol tests (shared, so every test seals alike).

A test that builds or corrupts a frame by hand wants its bytes to get past the CRC to
the checks behind it (header, fragment and msgpack parsers): :func:`sealed` appends the
CRC-16 the way docs/protocol.md §2 says, big-endian after the body; :func:`mutate` is the
fuzzers' edit of a frame.
"""

from __future__ import annotations

import random
from collections.abc import Sequence

from cellbridge.protocol import crc16


def sealed(body: bytes) -> bytes:
    """``body`` followed by its CRC-16 (big-endian): a frame, or a datagram's bytes, with a correct checksum."""
    return body + crc16(body).to_bytes(2, "big")


def mutate(rng: random.Random, data: bytes, corpus: Sequence[bytes]) -> bytes:
    """``data`` with one to four random edits (bytes set or flipped, cut, inserted, spliced
    with a frame of ``corpus``, a header field set to an extreme), resealed with a good CRC
    half of the time so that the edits reach the payload parsers."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(6)
        if op == 0 and b:
            b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 1 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 2:
            del b[rng.randrange(len(b) + 1):]
        elif op == 3:
            pos = rng.randrange(len(b) + 1)
            b[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif op == 4:
            other = rng.choice(corpus)
            cut = rng.randrange(len(other) + 1)
            b = b[:rng.randrange(len(b) + 1)] + bytearray(other[cut:])
        elif op == 5 and len(b) > 16:  # rewrite a header field with an extreme value
            pos = rng.randrange(14)
            b[pos] = rng.choice([0, 1, 0x0F, 0x10, 0x7F, 0x80, 0xFF])
    if rng.random() < 0.5 and len(b) >= 2:
        b = bytearray(sealed(bytes(b[:-2])))
    return bytes(b)
