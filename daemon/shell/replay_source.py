"""What a ``replay:FILE`` link reads: a capture file (``.cbcap``) or an MCAP recording.

An MCAP recording made with ``cellbridge record --serial`` keeps every gateway read on
its ``serial`` channel (``link``, ``t_host`` and the bytes, base64 in JSON); a daemon with
``url = "replay:FILE.mcap"`` re-runs its whole pipeline on them, read by read and at the
recorded arrival times, as from a capture file. The link takes the reads of the recorded
link with its own name, or, when the file holds one link only, that one. Capture files
(``CBCAP1``) are read as before (:mod:`cellbridge.daemon.shell.capture`). A recording cut short
(recorder killed) is read to its last whole chunk.
"""

from __future__ import annotations

import base64
import io
import json
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from cellbridge.daemon.core.mcap_chunks import MAX_RECORD_BYTES, ChunkDamage, check_chunk, decompress
from cellbridge.daemon.shell.capture import MAGIC as CAPTURE_MAGIC
from cellbridge.daemon.shell.capture import CaptureError, read_capture
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import StreamReader

MCAP_MAGIC = b"\x89MCAP0\r\n"
SERIAL_TOPIC = "serial"
#: Largest serial message read: a read is at most 64 KiB, base64 in JSON about 88 KiB.
MAX_SERIAL_MESSAGE = 256 << 10


def read_records(path: str | Path, link: str) -> Iterator[tuple[float, bytes]]:
    """(host time, bytes) of every read of ``link``; CaptureError for a file that is neither format."""
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic == CAPTURE_MAGIC:
        return read_capture(path)
    if magic == MCAP_MAGIC:
        return _mcap_serial(Path(path), link)
    raise CaptureError(f"{path}: neither a cellbridge capture nor an MCAP recording (bad magic)")


def serial_links(path: str | Path) -> dict[str, int]:
    """Reads per recorded link name on the file's serial channel."""
    out: dict[str, int] = {}
    for name, _, _ in _serial_messages(Path(path)):
        out[name] = out.get(name, 0) + 1
    return out


def _serial_messages(path: Path) -> Iterator[tuple[str, float, bytes]]:
    """(link, read time, bytes) of the serial channel's messages, in file order. Chunks are
    decompressed within the readers' limits (:mod:`cellbridge.daemon.core.mcap_chunks`): one
    beyond them, or unreadable, ends the reads with a CaptureError naming where. A file cut
    short (the recorder killed) ends quietly at its last whole record."""
    channels: set[int] = set()
    with open(path, "rb") as fh:
        outer = StreamReader(fh, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records
        while True:
            try:
                rec = next(outer)
            except (StopIteration, EndOfFile, struct.error):  # (a record cut short: the file ends there)
                return
            except McapError as exc:
                raise CaptureError(f"{path}: damaged at byte {fh.tell()}: {exc}") from None
            if isinstance(rec, Chunk):
                where = f"{path}: damaged chunk before byte {fh.tell()}"
                try:
                    check_chunk(len(rec.data), rec.uncompressed_size)
                    data = decompress(rec.compression, rec.data, rec.uncompressed_size)
                except ChunkDamage as exc:
                    raise CaptureError(f"{where}: {exc}") from None
                if len(data) != rec.uncompressed_size:
                    raise CaptureError(f"{where}: it expands to {'more' if len(data) > rec.uncompressed_size else 'less'}"
                                     f" than the {rec.uncompressed_size} bytes it declares")
                records: Iterator[Any] = _chunk_records(bytes(data))
            else:
                where, records = f"{path}: damaged at byte {fh.tell()}", iter([rec])
            while True:
                try:
                    r = next(records)
                except StopIteration:
                    break
                except (McapError, struct.error, ValueError) as exc:
                    raise CaptureError(f"{where}: {exc}") from None
                if isinstance(r, Channel) and r.topic == SERIAL_TOPIC:
                    channels.add(r.id)
                elif isinstance(r, Message) and r.channel_id in channels:
                    yield _serial_read(r.data, where)


def _chunk_records(data: bytes) -> Iterator[Channel | Message]:
    """The channels and messages of a chunk's decompressed records (others skipped);
    CaptureError for a record that runs past the chunk's end."""
    stream = ReadDataStream(io.BytesIO(data))
    end = len(data)
    while stream.count < end:
        if end - stream.count < 9:
            raise CaptureError("a record header cut short at the chunk's end")
        opcode, length = stream.read1(), stream.read8()
        if length > end - stream.count:
            raise CaptureError(f"a record of {length} bytes runs past the chunk's end")
        start = stream.count
        if opcode == Opcode.CHANNEL:
            yield Channel.read(stream)
        elif opcode == Opcode.MESSAGE:
            yield Message.read(stream, length)
        else:
            stream.read(length)
            continue
        if stream.count - start != length:
            raise CaptureError(f"a record declares {length} bytes and holds {stream.count - start}")


def _serial_read(data: bytes, where: str) -> tuple[str, float, bytes]:
    """(link, read time, bytes) of one serial message; CaptureError for one that is not."""
    if len(data) > MAX_SERIAL_MESSAGE:  # a read is at most READ_SIZE bytes: never JSON this large
        raise CaptureError(f"{where}: a serial message of {len(data)} bytes (at most {MAX_SERIAL_MESSAGE})")
    try:
        m = json.loads(data)
        # t_read: never stepped with the wall clock (recordings before it: t_host)
        return str(m.get("link", "")), float(m.get("t_read", m["t_host"])), base64.b64decode(m["data"])
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CaptureError(f"{where}: a serial message unreadable ({str(exc)[:80]})") from None


def _mcap_serial(path: Path, link: str) -> Iterator[tuple[float, bytes]]:
    names = serial_links(path)
    if not names:
        raise CaptureError(f"{path}: the recording has no serial channel (record with --serial)")
    if link not in names:
        if len(names) > 1:
            raise CaptureError(f"{path}: no serial reads of link {link!r} (recorded links: {', '.join(sorted(names))})")
        (link,) = names
    return ((t, data) for name, t, data in _serial_messages(path) if name == link)
