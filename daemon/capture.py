"""Capture files: a link's raw bytes exactly as read, each read with its host arrival time.

Keeping the read boundaries and times (not just the byte stream) is what lets a replay
feed the pipeline the very same batches at the very same times, so its output is
byte-for-byte reproducible and can be compared with a golden file.

Format (little-endian)::

    magic  8 bytes  b"CBCAP1\\n\\x00"
    record*         f64 host time (s since the epoch) | u32 length | bytes

A file cut short (daemon killed mid-write) reads up to its last whole record.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

MAGIC = b"CBCAP1\n\x00"
_REC = struct.Struct("<dI")
MAX_RECORD = 1 << 24


class CaptureWriter:
    """Never raises once open: a capture that fails (disk full, I/O error) stops, names
    its error and counts the records it could not keep. The line it records is what
    matters; a full disk must cost the capture, never ingest or health."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self.records = 0
        self.bytes = 0
        self.dropped = 0  # records not kept: buffered when the capture failed, or read since
        self.error = ""
        self._unflushed = 0
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
    """(time, bytes) of every whole record; ValueError if the file is not a capture."""
    with open(path, "rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"{path}: not a cellbridge capture file (bad magic)")
        while True:
            head = fh.read(_REC.size)
            if len(head) < _REC.size:
                return
            t, n = _REC.unpack(head)
            if n > MAX_RECORD:
                raise ValueError(f"{path}: corrupt record of {n} bytes")
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
