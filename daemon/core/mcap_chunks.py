"""How far a reader of an MCAP recording trusts a chunk: bounded decompression.

A recording is input like any other: an 8 kB file may declare a chunk of 256 MB, and a
few kB of zstd may expand to millions of tiny messages. Every reader of recordings (the
daemon's ``replay:FILE.mcap`` link, ``cellbridge info``, ``replay``, ``export``) holds to
these limits before it decompresses: a chunk larger than :data:`MAX_CHUNK_BYTES`, or
expanding more than :data:`MAX_RATIO` times beyond :data:`RATIO_FLOOR`, is damage, never
memory spent.
"""

from __future__ import annotations

import lz4.frame
import zstandard

#: Largest chunk (its records, uncompressed) a reader decompresses: a message of up to
#: 8 MB (the recorder's largest) on top of a full chunk of up to 8 MB (``--chunk-size``).
MAX_CHUNK_BYTES = 20 << 20
#: Most a chunk may expand (uncompressed : stored, beyond RATIO_FLOOR bytes). The daemon's
#: JSON compresses about 5:1; a decompression bomb (a few kB that expand to many MB of
#: tiny messages) would otherwise cost time out of all proportion to the file's size.
MAX_RATIO = 1000
RATIO_FLOOR = 64 << 10
#: Largest record a reader reads into memory (a chunk as stored: compressed, or not).
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + (1 << 20)


class ChunkDamage(ValueError):
    """A chunk a reader will not decompress (too large, expanding too much, unreadable)."""


def check_chunk(stored: int, uncompressed: int) -> None:
    """Raise :class:`ChunkDamage` for a chunk of ``stored`` bytes declaring ``uncompressed``."""
    if uncompressed > MAX_CHUNK_BYTES:
        raise ChunkDamage(f"a chunk declares {uncompressed} bytes (at most {MAX_CHUNK_BYTES} are read)")
    if uncompressed > MAX_RATIO * stored + RATIO_FLOOR:
        raise ChunkDamage(f"a chunk of {stored} bytes declares {uncompressed} (more than {MAX_RATIO}:1)")


def decompress(compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    """The chunk's records, never more than ``size`` + 1 bytes whatever the frame claims
    (a caller compares the length with ``size``); :class:`ChunkDamage` when unreadable."""
    if compression == "":
        return data
    try:
        if compression == "zstd":
            with zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True) as reader:
                out: bytes = reader.read(size + 1)
        elif compression == "lz4":
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
        else:
            raise ChunkDamage(f"unknown compression {compression[:20]!r}")
    except (zstandard.ZstdError, RuntimeError, ValueError, MemoryError) as exc:
        if isinstance(exc, ChunkDamage):
            raise
        raise ChunkDamage(f"{compression} data unreadable ({str(exc)[:80] or type(exc).__name__})") from None
    return out
