"""MCAP files of the daemon's topics: writing them so a kill loses little, reading what is there.

Writing goes through ``mcap.writer.Writer`` (chunked, zstd). Its output here is a file
written with ``os.write`` and no user-space buffer: every chunk the writer finishes is in
the kernel at once, so a recorder killed (SIGKILL) leaves a file that reads back up to its
last finished chunk; :meth:`RecordingWriter.flush` also finishes the chunk in progress
(the recorder does so every ``chunk_seconds``), bounding what a kill can lose in time as
well as in size. A power loss keeps what reached the disk (``fsync`` on each flush).

Reading (:func:`read_messages`) takes a finished file through its index, and a file that
was never finished (no summary, cut mid-chunk) by reading records in order up to the last
whole chunk; :class:`ReadResult` says which.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from cellbridge._version import __version__
from cellbridge.recording import schemas

PROFILE = ""  # no ROS profile: plain JSON channels
LIBRARY = f"cellbridge {__version__}"


class _UnbufferedFile:
    """What ``Writer`` writes to: each write goes to the kernel whole, or raises OSError."""

    def __init__(self, path: Path, fsync: bool) -> None:
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.pos = 0
        self._fsync = fsync

    def write(self, data: bytes | memoryview) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]
            self.pos += n
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        if self._fsync:
            os.fsync(self.fd)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


class RecordingWriter:
    """One MCAP file of daemon topics. Every method may raise OSError (disk full...);
    the recorder catches it, the file then reads up to its last flushed chunk."""

    def __init__(self, path: str | Path, *, chunk_size: int = 1 << 20, compression: str = "zstd",
                 fsync: bool = True, metadata: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        self._file = _UnbufferedFile(self.path, fsync)
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)  # type: ignore[arg-type]  # a file-like of our own (write, tell, flush), not an IO[bytes]
            self._writer.start(profile=PROFILE, library=LIBRARY)
            if metadata:
                self._writer.add_metadata("cellbridge", metadata)
        except BaseException:
            self._file.close()
            raise
        self._channels: dict[str, int] = {}
        self.messages = 0
        self.pending = 0  #: messages in the chunk being built (not in the file yet)
        self.first_ns: int | None = None
        self.finished = False

    @property
    def size(self) -> int:
        return self._file.tell()

    def channel(self, topic: str) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._writer.register_schema(f"cellbridge.{topic}", schemas.SCHEMA_ENCODING,
                                               schemas.schema_bytes(topic))
            ch = self._writer.register_channel(topic, schemas.MESSAGE_ENCODING, sid)
            self._channels[topic] = ch
        return ch

    def add(self, topic: str, data: bytes, log_ns: int, publish_ns: int, sequence: int = 0) -> None:
        """One JSON message (:func:`cellbridge.recording.codec.encode`)."""
        before = self._file.pos
        self._writer.add_message(self.channel(topic), log_time=log_ns, data=data, publish_time=publish_ns,
                                 sequence=sequence & 0xFFFFFFFF)
        # the writer finished a chunk (this message in it): on disk; else one more waits in memory
        self.pending = 0 if self._file.pos != before else self.pending + 1
        self.messages += 1
        if self.first_ns is None:
            self.first_ns = publish_ns

    def flush(self) -> None:
        """Finish the chunk in progress: everything added so far survives a kill."""
        self._writer.flush()
        self.pending = 0

    def finish(self) -> None:
        """Summary, index and footer: the file is complete (a viewer seeks in it)."""
        if not self.finished:
            self.finished = True
            try:
                self._writer.finish()
                self._file.flush()
            finally:
                self._file.close()

    def abandon(self) -> None:
        """Close without writing more (after a write error): the file keeps its whole chunks."""
        self.finished = True
        self._file.close()


@dataclass
class Recorded:
    topic: str
    data: bytes  # the message as stored (JSON)
    log_ns: int
    publish_ns: int
    sequence: int
    schema: Schema | None


@dataclass
class ReadResult:
    """How a file was read: ``complete`` (through its summary) or cut short, and where."""

    complete: bool = True
    error: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


def read_messages(path: str | Path, result: ReadResult | None = None,
                  topics: set[str] | None = None) -> Iterator[Recorded]:
    """Every message in the order it was recorded (the order the daemon published it).

    ValueError if the file is not MCAP at all; a file cut short yields what its whole
    chunks hold and sets ``result.complete = False`` and ``result.error``.
    """
    result = result if result is not None else ReadResult()
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{path}: not an MCAP file (bad magic)")
        fh.seek(0)
        summary = None
        try:
            reader = make_reader(fh)
            summary = reader.get_summary()
        except (McapError, struct.error, ValueError, EOFError):
            summary = None
        if summary is not None and summary.chunk_indexes:
            try:
                result.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            except (McapError, struct.error, ValueError):
                pass
            for schema, channel, msg in reader.iter_messages(topics=topics, log_time_order=False):
                yield Recorded(channel.topic, msg.data, msg.log_time, msg.publish_time, msg.sequence, schema)
            return
        fh.seek(0)
        yield from _read_stream(fh, result, topics, path)


def _read_stream(fh: Any, result: ReadResult, topics: set[str] | None, path: str | Path) -> Iterator[Recorded]:
    schemas_by_id: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    records = StreamReader(fh, validate_crcs=True).records
    while True:
        try:
            rec = next(records)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - a cut file ends in any of the reader's errors
            result.complete = False
            result.error = f"{path}: file ends without its summary (recording cut short): {type(exc).__name__}"
            return
        if isinstance(rec, Schema):
            schemas_by_id[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is None or (topics is not None and ch.topic not in topics):
                continue
            yield Recorded(ch.topic, rec.data, rec.log_time, rec.publish_time, rec.sequence,
                           schemas_by_id.get(ch.schema_id))
        elif type(rec).__name__ == "Metadata":
            result.metadata[rec.name] = dict(rec.metadata)  # type: ignore[attr-defined]  # a Metadata record, matched by its class name
