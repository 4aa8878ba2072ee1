"""MCAP files of the daemon's topics: writing them so a kill loses little, reading what is there.

Writing goes through ``mcap.writer.Writer`` (chunked, zstd). Its output here is a file
written with ``os.write`` and no user-space buffer: every chunk the writer finishes is in
the kernel at once, so a recorder killed (SIGKILL) leaves a file that reads back up to its
last finished chunk; :meth:`RecordingWriter.flush` also finishes the chunk in progress
(the recorder does so every ``chunk_seconds``), bounding what a kill can lose in time as
well as in size. A power loss keeps what reached the disk (``fsync`` on each flush).

Reading (:func:`read_messages`) goes through the records in file order (the order the
messages were received), a file that was never finished (no summary, cut mid-chunk) up to
its last whole chunk. A recording is input like any other, so the reader bounds what it
takes before it takes it: a record's declared length against the file and
:data:`MAX_RECORD_BYTES`, a chunk's declared size against :data:`MAX_CHUNK_BYTES` and
against :data:`MAX_RATIO` times what it stores, and decompression stops one byte past
the declared size (a zstd or lz4 frame may claim anything). A damaged part (a chunk
that does not decompress or fails its CRC, a record that does not parse, framing that
runs off) is skipped, counted and described in
:class:`ReadResult`, and reading goes on after it (with the file's index, at the next
chunk); what can be read is read. Nothing but :class:`NotARecording` (not MCAP at all, or
a ROS 2 bag's file) and ``OSError`` leaves the reader.
"""

from __future__ import annotations

import bisect
import io
import os
import stat
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mcap.writer
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Metadata
from mcap.writer import CompressionType, Writer

from cellbridge._version import __version__
from cellbridge.daemon.core.mcap_chunks import (
    MAX_CHUNK_BYTES,
    MAX_RATIO,
    MAX_RECORD_BYTES,
    RATIO_FLOOR,
    ChunkDamage,
    decompress,
)
from cellbridge.recording import schemas

MAGIC = b"\x89MCAP0\r\n"
# The limits on chunks and records, shared with the daemon's replay link:
# MAX_CHUNK_BYTES, MAX_RATIO, RATIO_FLOOR, MAX_RECORD_BYTES (daemon/core/mcap_chunks.py).
#: Longest topic name read (the daemon's are a word); metadata records kept (larger ones
#: and more are not kept: nothing reads them but a person).
MAX_TOPIC = 200
MAX_METADATA = 64 << 10
MAX_METADATA_RECORDS = 64
#: Largest chunk size the writer is given (``cellbridge record --chunk-size``).
MAX_CHUNK_SIZE = 8_000_000

PROFILE = ""  # no ROS profile: plain JSON channels

#: zstd's skippable frame: a magic number, the length of the bytes that follow; every zstd
#: decoder passes over it.
_SKIPPABLE = struct.Struct("<II")
_SKIPPABLE_MAGIC = 0x184D2A50


def compress_within_ratio(data: bytes) -> bytes:
    """zstd of a chunk's records, padded (a skippable frame after the compressed one) so that
    it stores at least 1 byte per :data:`MAX_RATIO` beyond :data:`RATIO_FLOOR`: every reader
    (``info``, ``replay``, the daemon's replay link) takes a chunk that expands more as a
    decompression bomb, and messages that repeat themselves (identical readings of a large
    skin) compress past that. The padding costs at most a thousandth of the chunk."""
    out: bytes = zstandard.compress(data)
    need = (len(data) - RATIO_FLOOR) // MAX_RATIO + 1 - len(out)
    if need > 0:
        pad = max(0, need - _SKIPPABLE.size)
        out += _SKIPPABLE.pack(_SKIPPABLE_MAGIC, pad) + bytes(pad)
    return out


class _ChunkZstd:
    """What the ``mcap`` package's writer calls ``zstandard``: its chunks compressed by
    :func:`compress_within_ratio` (it compresses each chunk with ``zstandard.compress``), so
    every MCAP file cellbridge writes (recordings, ROS 2 bags) reads back in its readers."""

    compress = staticmethod(compress_within_ratio)


mcap.writer.zstandard = _ChunkZstd  # type: ignore[assignment]
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
    offset: int = 0  # where in the file: its chunk's (or its own record's) first byte


class NotARecording(ValueError):
    """The file is not MCAP at all (its first bytes are not MCAP's magic), or is the MCAP
    file of a ROS 2 bag (``record --profile ros2``: CDR messages, which are not the JSON
    payloads every message here is read as: each would be skipped as damaged)."""


#: The MCAP profile of a ROS 2 bag's files (``cellbridge/ros2/bag.py`` and rosbag2 write it).
ROS2_PROFILE = b"ros2"


#: Parts of a damaged file described one by one in :attr:`ReadResult.damage` (the rest counted).
DAMAGE_KEPT = 5


@dataclass
class ReadResult:
    """How a file was read.

    ``complete``: read through its footer (else cut short: ``error`` says so, naming the
    file). ``damaged``: parts that could not be read (a chunk, a record, the rest of the
    file after framing that ran off, the index), the first few described in ``damage``;
    ``bad_messages``: messages skipped because their payload could not be decoded (filled
    in by :func:`read_payloads`). Messages of the damaged parts are lost, every other one
    is read.
    """

    complete: bool = True
    error: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    damaged: int = 0
    bad_messages: int = 0
    damage: list[str] = field(default_factory=list)
    messages: int = 0  #: messages read

    def add_damage(self, where: str) -> None:
        self.damaged += 1
        if len(self.damage) < DAMAGE_KEPT:
            self.damage.append(where)

    def add_bad_message(self, where: str) -> None:
        self.bad_messages += 1
        if len(self.damage) < DAMAGE_KEPT:
            self.damage.append(where)

    @property
    def ok(self) -> bool:
        """Nothing damaged and no message skipped (a file cut short can be ok)."""
        return not (self.damaged or self.bad_messages)

    def problem(self, path: str | Path) -> str:
        """One line naming the file and what was wrong with it ("" when it is :attr:`ok`)."""
        if self.ok:
            return ""
        parts = []
        if self.damaged:
            parts.append(f"{self.damaged} damaged part{'s' if self.damaged != 1 else ''} skipped")
        if self.bad_messages:
            parts.append(f"{self.bad_messages} unreadable message{'s' if self.bad_messages != 1 else ''} skipped")
        first = "; ".join(self.damage[:2])
        return f"{path}: damaged: {', '.join(parts)} ({first}); {self.messages - self.bad_messages} messages read"


class _Damage(Exception):
    """One part of the file cannot be read (internal: becomes an entry of ReadResult)."""


_HEAD = struct.Struct("<BQ")  # opcode, record length
_CHUNK_HEAD = struct.Struct("<QQQII")  # start time, end time, uncompressed size, crc, compression length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_FOOTER = struct.Struct("<BQQQI8s")  # opcode, length 20, summary start, summary offset start, crc, magic


def _parse(cls: Any, body: bytes) -> Any:
    """A small record through the mcap package's own parser, fed only this record's bytes
    (a damaged inner length cannot make it read past them)."""
    stream = ReadDataStream(io.BytesIO(body))
    try:
        return cls.read(stream)
    except (McapError, struct.error, ValueError, OverflowError) as exc:  # ValueError: UnicodeDecodeError too
        raise _Damage(f"{cls.__name__.lower()} record does not parse ({type(exc).__name__})") from None


def _decompress(compression: str, data: memoryview, size: int) -> bytes | memoryview:
    """The chunk's records, never more than ``size`` + 1 bytes whatever the frame claims."""
    try:
        return decompress(compression, data, size)
    except ChunkDamage as exc:
        raise _Damage(str(exc)) from None


class _Index:
    """What a finished file's summary says about its chunks: where each starts (to go on
    after damage, and to tell a chunk that was never reached), and, when its CRC holds,
    the channels in each (to skip chunks of other topics)."""

    def __init__(self) -> None:
        self.starts: list[int] = []  # sorted
        self.lengths: list[int] = []  # of each chunk's record, opcode and length field included
        self.channels: dict[int, frozenset[int]] = {}  # chunk start -> channel ids in it (reading some topics)
        self.topics: dict[int, str] = {}  # channel id -> topic
        self.trusted = False

    def chunks_after(self, after: int) -> Iterator[int]:
        for i in range(bisect.bisect_right(self.starts, after), len(self.starts)):
            yield self.starts[i]


class _Reader:
    def __init__(self, fh: Any, path: str | Path, result: ReadResult, topics: set[str] | None) -> None:
        self.fh = fh
        self.path = path
        self.result = result
        self.topics = topics
        self.size = os.fstat(fh.fileno()).st_size
        self.channels: dict[int, str] = {}
        self.index = _Index()
        self.footer_at: int | None = None  # where the footer record starts (a finished file)

    def _read_at(self, pos: int, n: int) -> bytes:
        self.fh.seek(pos)
        return bytes(self.fh.read(n))

    def _chunk_at(self, pos: int, end: int) -> bool:
        """Whether the index's chunk at ``pos`` is there: a chunk record of the length the index
        gives (a file spliced after it was finished has its chunks elsewhere)."""
        head = self._read_at(pos, _HEAD.size)
        if len(head) < _HEAD.size:
            return False
        opcode, length = _HEAD.unpack(head)
        i = bisect.bisect_left(self.index.starts, pos)
        return opcode == Opcode.CHUNK and i < len(self.index.starts) and self.index.starts[i] == pos \
            and _HEAD.size + length == self.index.lengths[i] and pos + _HEAD.size + length <= end

    def _next_chunk(self, after: int, end: int, before: int | None = None) -> int | None:
        """The first chunk the index names after ``after`` (and before ``before``) that is there."""
        for c in self.index.chunks_after(after):
            if c >= end or (before is not None and c >= before):
                return None
            if self._chunk_at(c, end):
                return c
        return None

    # -- the end of the file: footer and summary ------------------------------------------
    def read_footer(self) -> None:
        at = self.size - _FOOTER.size
        if at < len(MAGIC):
            return
        opcode, length, summary_start, _, crc, magic = _FOOTER.unpack(self._read_at(at, _FOOTER.size))
        if opcode != Opcode.FOOTER or length != 20 or magic != MAGIC:
            return
        self.footer_at = at
        if summary_start == 0:
            return
        if not len(MAGIC) <= summary_start < at:
            self.result.add_damage(f"footer at byte {at}: summary start {summary_start} outside the file")
            return
        try:
            self._read_summary(summary_start, at, crc)
        except _Damage as exc:
            self.result.add_damage(f"summary at byte {summary_start}: {exc}")
            self.index = _Index()

    def _read_summary(self, start: int, end: int, crc: int) -> None:
        index = _Index()
        running = 0
        pos = start
        chunks: list[tuple[int, int]] = []
        chunk_channels: dict[int, frozenset[int]] = {}
        shared: dict[frozenset[int], frozenset[int]] = {}
        while pos < end:
            head = self._read_at(pos, _HEAD.size)
            if len(head) < _HEAD.size:
                raise _Damage("ends inside a record")
            opcode, length = _HEAD.unpack(head)
            if pos + _HEAD.size + length > end or length > MAX_RECORD_BYTES:
                raise _Damage(f"record at byte {pos} runs past the footer")
            body = self._read_at(pos + _HEAD.size, length)
            running = zlib.crc32(body, zlib.crc32(head, running))
            if opcode == Opcode.CHUNK_INDEX:
                ci: ChunkIndex = _parse(ChunkIndex, body)
                if ci.chunk_start_offset < self.size:
                    chunks.append((ci.chunk_start_offset, ci.chunk_length))
                    if self.topics is not None:
                        ids = frozenset(ci.message_index_offsets)
                        chunk_channels[ci.chunk_start_offset] = shared.setdefault(ids, ids)
            elif opcode == Opcode.CHANNEL:
                ch: Channel = _parse(Channel, body)
                index.topics[ch.id] = ch.topic[:MAX_TOPIC + 1]
            pos += _HEAD.size + length
        running = zlib.crc32(self._read_at(end, 1 + 8 + 8 + 8), running)
        chunks.sort()
        index.starts = [c for c, _ in chunks]
        index.lengths = [n for _, n in chunks]
        if crc != 0 and running != crc:
            self.result.add_damage(f"summary at byte {start}: CRC mismatch (the index is not used)")
            return
        index.trusted = crc != 0 and bool(index.starts)
        index.channels = chunk_channels
        self.index = index

    # -- the data section, record by record -----------------------------------------------
    def messages(self) -> Iterator[Recorded]:
        end = self.footer_at if self.footer_at is not None else self.size
        pos = len(MAGIC)
        starts = self.index.starts if self.index.trusted else []
        passed = 0  # of the index's chunks (in file order), those the reading has come to
        lost = 0  # ... and of those, the ones not found where the index says
        first_lost = 0
        while pos < end:
            head = self._read_at(pos, _HEAD.size)
            if len(head) < _HEAD.size:
                if self.footer_at is None:
                    self._cut_short("inside a record's header")
                else:
                    self.result.add_damage(f"byte {pos}: record header runs into the footer")
                break
            opcode, length = _HEAD.unpack(head)
            rec_end = pos + _HEAD.size + length
            # a chunk of the index inside this record: its length is wrong (damaged framing)
            inside = self._next_chunk(pos, end, before=rec_end) if self.index.trusted else None
            if rec_end > end or inside is not None or opcode == 0:
                if self.footer_at is None and rec_end > end and opcode != 0:
                    self._cut_short(f"inside a record of {length} bytes at byte {pos}")
                    break
                self.result.add_damage(f"byte {pos}: a record of {length} bytes (opcode {opcode:#x}) "
                                       f"does not fit: framing lost")
                nxt = inside if inside is not None else self._next_chunk(pos, end)
                if nxt is None:
                    break
                pos = nxt
                continue
            if opcode == Opcode.DATA_END:
                break
            try:
                if opcode == Opcode.CHUNK:
                    while passed < len(starts) and starts[passed] <= pos:
                        if starts[passed] < pos:
                            first_lost = first_lost or starts[passed]
                            lost += 1
                        passed += 1
                    yield from self._chunk(pos, length)
                elif opcode in (Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA):
                    if length > MAX_RECORD_BYTES:
                        raise _Damage(f"declares {length} bytes, more than the {MAX_RECORD_BYTES} a record may have")
                    body = self._read_at(pos + _HEAD.size, length)
                    if opcode == Opcode.MESSAGE:
                        m = self._message(memoryview(body), pos)
                        if m is not None:
                            yield m
                    else:
                        self._other(opcode, body)
            except _Damage as exc:
                self.result.add_damage(f"{_NAMES.get(opcode, 'record')} at byte {pos}: {exc}")
            pos = rec_end
        if passed < len(starts):
            first_lost = first_lost or starts[passed]
            lost += len(starts) - passed
        if lost:
            self.result.add_damage(f"{lost} chunk{'s' if lost != 1 else ''} of the index not read "
                                   f"where it says (first at byte {first_lost})")
        if self.footer_at is None and self.result.complete:
            self._cut_short(f"after byte {pos}")

    def _cut_short(self, where: str) -> None:
        self.result.complete = False
        self.result.error = f"{self.path}: file ends without its summary (recording cut short): {where}"

    def _other(self, opcode: int, body: bytes) -> None:
        if opcode == Opcode.CHANNEL:
            ch: Channel = _parse(Channel, body)
            if len(ch.topic) > MAX_TOPIC:
                raise _Damage(f"channel {ch.id}: a topic of {len(ch.topic)} characters")
            self.channels[ch.id] = ch.topic
        elif opcode == Opcode.METADATA and len(body) <= MAX_METADATA and len(self.result.metadata) < MAX_METADATA_RECORDS:
            md: Metadata = _parse(Metadata, body)
            self.result.metadata[md.name] = dict(md.metadata)

    def _message(self, body: memoryview, offset: int) -> Recorded | None:
        if len(body) < _MESSAGE_HEAD.size:
            raise _Damage(f"message record of {len(body)} bytes, shorter than its header")
        channel, seq, log_ns, publish_ns = _MESSAGE_HEAD.unpack_from(body)
        topic = self.channels.get(channel)
        if topic is None and self.index.trusted:  # defined in a chunk skipped for its topics
            topic = self.index.topics.get(channel)
        if topic is None:
            raise _Damage(f"message on channel {channel}, which no channel record defines")
        if self.topics is not None and topic not in self.topics:
            return None
        self.result.messages += 1
        return Recorded(topic, bytes(body[_MESSAGE_HEAD.size:]), log_ns, publish_ns, seq, offset)

    def _chunk(self, pos: int, length: int) -> Iterator[Recorded]:
        if length > MAX_RECORD_BYTES:
            raise _Damage(f"declares {length} bytes, more than the {MAX_RECORD_BYTES} a chunk may have")
        if self.topics is not None and self.index.trusted and pos in self.index.channels:
            if not any(self.index.topics.get(c) in self.topics for c in self.index.channels[pos]):
                return  # the index says it holds none of the topics read
        body = memoryview(self._read_at(pos + _HEAD.size, length))
        if len(body) < _CHUNK_HEAD.size:
            raise _Damage("shorter than its header")
        _, _, size, crc, name_len = _CHUNK_HEAD.unpack_from(body)
        at = _CHUNK_HEAD.size
        if size > MAX_CHUNK_BYTES:
            raise _Damage(f"declares {size} bytes uncompressed, more than the {MAX_CHUNK_BYTES} a chunk may have")
        if name_len > 16 or at + name_len + 8 > len(body):
            raise _Damage("compression name does not fit")
        try:
            compression = str(body[at:at + name_len], "utf-8")
        except UnicodeDecodeError:
            raise _Damage("compression name is not text") from None
        at += name_len
        (data_len,) = struct.unpack_from("<Q", body, at)
        at += 8
        if data_len > len(body) - at:
            raise _Damage(f"declares {data_len} bytes of data, {len(body) - at} are there")
        if size > MAX_RATIO * data_len + RATIO_FLOOR:
            raise _Damage(f"declares {size} bytes uncompressed from {data_len}: more than {MAX_RATIO}:1 "
                          "(a decompression bomb)")
        data = _decompress(compression, body[at:at + data_len], size)
        del body
        if len(data) > size:
            raise _Damage(f"expands to more than the {size} bytes it declares")
        if len(data) < size:
            raise _Damage(f"expands to {len(data)} bytes, {size} declared")
        if crc != 0 and zlib.crc32(data) != crc:
            raise _Damage("CRC mismatch")
        yield from self._chunk_records(memoryview(data), pos)

    def _chunk_records(self, data: memoryview, pos: int) -> Iterator[Recorded]:
        at = 0
        while at < len(data):
            if at + _HEAD.size > len(data):
                raise _Damage(f"a record header runs past its end at byte {at}")
            opcode, length = _HEAD.unpack_from(data, at)
            start, at = at + _HEAD.size, at + _HEAD.size + length
            if at > len(data):
                raise _Damage(f"a record of {length} bytes runs past its end")
            try:
                if opcode == Opcode.MESSAGE:
                    m = self._message(data[start:at], pos)
                    if m is not None:
                        yield m
                elif opcode == Opcode.CHANNEL:
                    self._other(opcode, bytes(data[start:at]))
            except _Damage as exc:  # this record only: the chunk's framing still holds
                self.result.add_damage(f"chunk at byte {pos}: {exc}")


_NAMES = {Opcode.CHUNK: "chunk", Opcode.MESSAGE: "message", Opcode.CHANNEL: "channel", Opcode.METADATA: "metadata"}


def _profile(fh: Any) -> bytes | None:
    """The profile of the header record that follows the magic (None: no such record)."""
    head = fh.read(_HEAD.size)
    if len(head) < _HEAD.size:
        return None
    opcode, length = _HEAD.unpack(head)
    body = fh.read(min(length, 4 + 64)) if opcode == Opcode.HEADER else b""
    if len(body) < 4:
        return None
    (n,) = struct.unpack_from("<I", body)
    return bytes(body[4:4 + n]) if n <= 64 else None


def read_messages(path: str | Path, result: ReadResult | None = None,
                  topics: set[str] | None = None) -> Iterator[Recorded]:
    """Every message in the order it was recorded (the order the daemon published it).

    :class:`NotARecording` (a ValueError) if the file is not MCAP at all; OSError if it
    cannot be read. Anything else wrong with it is recorded in ``result`` and reading goes
    on: a file cut short yields what its whole chunks hold (``result.complete`` False,
    ``result.error`` says so), a damaged part is skipped (``result.damaged``,
    ``result.damage``). Memory is bounded by :data:`MAX_RECORD_BYTES` and
    :data:`MAX_CHUNK_BYTES` whatever the file declares.
    """
    result = result if result is not None else ReadResult()
    mode = os.stat(path).st_mode
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # a FIFO would be waited on for ever, a device read without end
        raise NotARecording(f"{path}: not a regular file (a FIFO or a device): not read")
    with open(path, "rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            raise NotARecording(f"{path}: not an MCAP file (bad magic)")
        if _profile(fh) == ROS2_PROFILE:
            raise NotARecording(f"{path}: a ROS 2 bag's file (cellbridge record --profile ros2; CDR messages): "
                                "read the bag with ros2 bag, rosbags or Foxglove")
        reader = _Reader(fh, path, result, topics)
        reader.read_footer()
        yield from reader.messages()


def read_payloads(path: str | Path, result: ReadResult | None = None,
                  topics: set[str] | None = None) -> Iterator[tuple[Recorded, dict[str, Any]]]:
    """:func:`read_messages` with each message decoded (:func:`codec.decode`); a message that
    does not decode is skipped and counted in ``result.bad_messages``."""
    from cellbridge.recording import codec

    result = result if result is not None else ReadResult()
    for m in read_messages(path, result, topics):
        try:
            payload = codec.decode(m.topic, m.data)
        except codec.PayloadError as exc:
            result.add_bad_message(f"a message on {m.topic[:40]!r} (chunk at byte {m.offset}): {exc}")
            continue
        yield m, payload
