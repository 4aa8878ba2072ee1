"""Capture files: a link's raw bytes exactly as read, each read with its host arrival time.

Keeping the read boundaries and times (not just the byte stream) is what lets a replay
feed the pipeline the very same batches at the very same times, so its output is
byte-for-byte reproducible and can be compared with a golden file.

Format (little-endian)::

    magic  8 bytes  b"CBCAP1\\n\\x00"
    record*         f64 host time (s since the epoch) | u32 length | bytes

The host time is the wall clock's at the capture's start, then the monotonic clock's, so
a wall-clock step during the capture does not enter it (a replay in recorded time takes
these times as its one time base).

A file cut short (daemon killed mid-write) reads up to its last whole record.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from cellbridge.errors import CellbridgeError

MAGIC = b"CBCAP1\n\x00"
_REC = struct.Struct("<dI")
MAX_RECORD = 1 << 24


def capture_problem(path: str | Path) -> str | None:
    """Why a capture could not be written at ``path`` (None: it can), for ``--check``."""
    p = Path(path)
    if p.is_dir():
        return "is a directory"
    parent = p.parent
    if not parent.is_dir():
        return f"directory {str(parent)!r} does not exist"
    if p.exists() and not p.is_file():  # a device or a pipe is written to as it is
        return None if os.access(p, os.W_OK) else "not writable"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"directory {str(parent)!r} is not writable (a capture is created there, an old one renamed)"
    return None


def rotate(path: Path) -> Path | None:
    """Move a non-empty capture out of the way as ``PATH.N`` (N one above the highest
    there), so a restart never overwrites what the last run recorded; returns where it went."""
    try:
        if not path.is_file() or path.stat().st_size == 0:
            return None
    except OSError:
        return None
    taken = [int(q.name[len(path.name) + 1:]) for q in path.parent.glob(path.name + ".*")
             if q.name[len(path.name) + 1:].isdigit()]
    target = path.with_name(f"{path.name}.{max(taken, default=0) + 1}")
    path.rename(target)
    return target


class CaptureError(CellbridgeError, ValueError):
    """A capture or recording that cannot be replayed (not one, damaged, no serial reads of
    the link asked for): the message names the file and what is wrong. A replay link
    reports it and ends; a bug's ValueError is not one."""


class CaptureWriter:
    """Never raises: a capture that cannot be opened, or fails later (disk full, I/O
    error), stops, names its error (health ``capture_error``) and counts the records it
    could not keep. The line it records is what matters; a capture must never cost
    ingest, health, or the daemon's start.

    A non-empty file already at ``path`` (the last run's capture) is first renamed to
    ``PATH.1``, ``PATH.2``, ... (:func:`rotate`), never truncated.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.records = 0
        self.bytes = 0
        self.dropped = 0  # records not kept: buffered when the capture failed, or read since
        self.error = ""
        self._unflushed = 0
        self.rotated_to: Path | None = None
        self._fh: BinaryIO | None = None
        try:
            self.rotated_to = rotate(self.path)
            self._fh = open(self.path, "wb")
        except OSError as exc:
            self.error = f"{self.path}: cannot open: {exc.strerror or exc}"
            return
        self._guard(lambda fh: fh.write(MAGIC))

    def _guard(self, op: Callable[[BinaryIO], object]) -> bool:
        if self._fh is None:
            return False
        try:
            op(self._fh)
            return True
        except OSError as exc:
            self.error = f"{self.path}: {exc.strerror or exc}"
            self.dropped += self._unflushed
            self._unflushed = 0
            fh, self._fh = self._fh, None
            try:
                fh.close()
            except OSError:
                pass  # what is still buffered cannot be written either
            return False

    def write(self, t: float, data: bytes) -> None:
        if self._fh is None:
            self.dropped += bool(self.error)
            return
        self._unflushed += 1
        if self._guard(lambda fh: (fh.write(_REC.pack(t, len(data))), fh.write(data))):
            self.records += 1
            self.bytes += len(data)

    def flush(self) -> None:
        if self._guard(lambda fh: fh.flush()):
            self._unflushed = 0

    def close(self) -> None:
        self.flush()
        if self._fh is not None:
            self._guard(lambda fh: fh.close())
            self._fh = None

    def stats(self) -> dict[str, object]:
        return {"capture_records": self.records, "capture_dropped": self.dropped, "capture_error": self.error}


def read_capture(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """(time, bytes) of every whole record; :class:`CaptureError` if the file is not a
    capture or a record's length is corrupt (a record cut short at the end is the end)."""
    with open(path, "rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            raise CaptureError(f"{path}: not a cellbridge capture file (bad magic)")
        while True:
            head = fh.read(_REC.size)
            if len(head) < _REC.size:
                return
            t, n = _REC.unpack(head)
            if n > MAX_RECORD:
                raise CaptureError(f"{path}: corrupt record of {n} bytes")
            data = fh.read(n)
            if len(data) < n:
                return
            yield t, data


def write_capture(path: str | Path, records: list[tuple[float, bytes]]) -> None:
    w = CaptureWriter(path)
    try:
        for t, data in records:
            w.write(t, data)
    finally:
        w.close()
