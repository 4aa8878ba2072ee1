"""Serial-line framing: COBS-encoded frames separated by 0x00.

COBS removes every zero byte from a frame, so 0x00 marks frame boundaries
unambiguously: after any corruption the decoder loses at most the frame in
progress and is back in step at the next delimiter. The encoder writes a
delimiter *before* and after each frame so a receiver that joins mid-stream (or
after line noise) discards only the garbage up to the first delimiter.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.frame import MAX_FRAME, MIN_FRAME, Frame, decode, encode
from cobs import cobs

DELIMITER = b"\x00"
WINDOW = 65536  #: bytes of a fed chunk split at once: bounds what one feed call holds


def max_encoded_len(frame_len: int) -> int:
    """Longest COBS encoding of ``frame_len`` bytes (one overhead byte per 254)."""
    return frame_len + frame_len // 254 + 1


def encode_stream(frame: Frame) -> bytes:
    """One frame as serial-line bytes: ``00 cobs(frame) 00``."""
    return DELIMITER + cobs.encode(encode(frame)) + DELIMITER


class StreamDecoder:
    """Incremental decoder for the serial byte stream.

    ``feed(chunk)`` accepts any slice of the stream (one byte or a megabyte) and
    returns the frames completed so far. Bytes held between calls never exceed
    ``max_buffer``: an over-long run without a delimiter is discarded and the
    decoder skips to the next delimiter. Nothing is dropped silently:
    ``bytes_dropped`` and ``frames_dropped`` count by cause, ``frames_ok`` counts
    delivered frames, ``delimiters`` the 0x00 bytes. Every byte fed is accounted for:
    ``bytes_in == bytes_ok + sum(bytes_dropped) + delimiters + buffered``.

    Causes: ``overlong`` (more bytes than any valid frame before a delimiter),
    ``cobs`` (invalid COBS), and the :class:`ProtocolError` causes of
    :func:`decode` (``crc``, ``short``, ``version``, ...).

    ``readout``: :func:`decode`'s reader of READOUT payloads (None: the plain messages).
    """

    def __init__(self, max_frame: int = MAX_FRAME, readout: Callable[[bytes], Any] | None = None) -> None:
        self.max_buffer = max_encoded_len(max_frame)
        self.readout = readout
        self._buf = bytearray()
        self._skipping = False  # inside an over-long run: discard until the next delimiter
        self._skip_cause = "overlong"  # what the skipped bytes are counted as
        self.frames_ok = 0
        self.bytes_ok = 0  # COBS bytes of delivered frames
        self.bytes_in = 0
        self.delimiters = 0  # 0x00 bytes seen, frame boundaries and idle fill alike
        self.frames_dropped: Counter[str] = Counter()
        self.bytes_dropped: Counter[str] = Counter()

    @property
    def buffered(self) -> int:
        """Bytes held for the frame in progress (at most ``max_buffer``)."""
        return len(self._buf)

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Frame]:
        """The frames completed by ``chunk`` (any length: it is scanned in bounded windows).

        A Frame object takes ~10x its wire size; to hold none of them, use :meth:`feed_iter`.
        """
        out: list[Frame] = []
        if type(chunk) is bytes and len(chunk) <= WINDOW:  # (a read of a line: one window, no generator)
            self.bytes_in += len(chunk)
            self._scan(chunk, out)
            return out
        for piece in self._windows(chunk):
            self._scan(piece, out)
        return out

    def feed_iter(self, chunk: bytes | bytearray | memoryview) -> Iterator[Frame]:
        """The frames completed by ``chunk``, yielded a window (``WINDOW`` bytes) at a time.

        Consume it to the end before feeding more: the decoder state moves with it. A
        consumer that stops early (``break``, an exception) leaves frames and bytes it never
        took: they are counted ``abandoned``, and the decoder resumes at the next delimiter.
        """
        total = len(chunk) if type(chunk) is bytes else memoryview(chunk).nbytes
        out: list[Frame] = []
        sizes: list[int] = []
        taken = scanned = 0
        try:
            for piece in self._windows(chunk):
                self._scan(piece, out, sizes)
                scanned += len(piece)
                for taken, frame in enumerate(out, 1):  # noqa: B007 (taken is read in finally)
                    yield frame
                out.clear()
                sizes.clear()
                taken = 0
        finally:
            self._abandon(len(out) - taken, sum(sizes[taken:]), total - scanned)

    def _abandon(self, frames: int, frame_bytes: int, unscanned: int) -> None:
        """Count what a consumer of :meth:`feed_iter` left: decoded frames and unread bytes."""
        if frames:
            self.frames_ok -= frames
            self.bytes_ok -= frame_bytes
            self.frames_dropped["abandoned"] += frames
            self.bytes_dropped["abandoned"] += frame_bytes
        if unscanned:  # the frame in progress continues in bytes never read: resynchronise
            self.bytes_dropped["abandoned"] += unscanned + len(self._buf)
            self._buf.clear()
            self._skipping, self._skip_cause = True, "abandoned"

    def _windows(self, chunk: bytes | bytearray | memoryview) -> Iterator[bytes]:
        """``chunk`` in slices of at most ``WINDOW`` bytes, so that splitting at the
        delimiters (fast, in C) never holds more than one window's segments."""
        if type(chunk) is bytes and len(chunk) <= WINDOW:
            self.bytes_in += len(chunk)
            yield chunk
            return
        view = memoryview(chunk).cast("B")  # bytes, whatever the item size of a view fed
        self.bytes_in += len(view)
        for start in range(0, len(view), WINDOW):
            yield bytes(view[start:start + WINDOW])

    def _scan(self, piece: bytes, out: list[Frame], sizes: list[int] | None = None) -> None:
        parts = piece.split(DELIMITER)
        self.delimiters += len(parts) - 1
        # Every part but the last ended at a delimiter; the last is the frame in progress.
        last = parts.pop()
        for part in parts:
            if self._skipping:
                self.bytes_dropped[self._skip_cause] += len(part)
                self._skipping = False
            elif self._buf:
                self._buf += part
                part = bytes(self._buf)
                self._buf.clear()
                self._frame(part, out, sizes)
            elif part:
                self._frame(part, out, sizes)
        if self._skipping:
            self.bytes_dropped[self._skip_cause] += len(last)
        elif len(self._buf) + len(last) > self.max_buffer:
            self._overlong(len(self._buf) + len(last))
        else:
            self._buf += last

    def _overlong(self, size: int) -> None:
        """Discard a run longer than any frame: the bytes so far, and the rest up to the next delimiter."""
        self.bytes_dropped["overlong"] += size
        self.frames_dropped["overlong"] += 1
        self._buf.clear()
        self._skipping, self._skip_cause = True, "overlong"

    def _frame(self, encoded: bytes, out: list[Frame], sizes: list[int] | None) -> None:
        if len(encoded) > self.max_buffer:
            self._dropped("overlong", len(encoded))
            return
        try:
            raw = cobs.decode(encoded)
        except cobs.DecodeError:
            self._dropped("cobs", len(encoded))
            return
        if len(raw) < MIN_FRAME:  # the commonest garbage, counted without raising
            self._dropped("short", len(encoded))
            return
        try:
            out.append(decode(raw, self.readout))
        except ProtocolError as exc:
            self._dropped(exc.cause, len(encoded))
            return
        self.frames_ok += 1
        self.bytes_ok += len(encoded)
        if sizes is not None:
            sizes.append(len(encoded))

    def _dropped(self, cause: str, size: int) -> None:
        self.bytes_dropped[cause] += size
        self.frames_dropped[cause] += 1

    def counters(self) -> dict[str, object]:
        """A snapshot for health reports: totals and drops by cause."""
        return {
            "bytes_in": self.bytes_in,
            "frames_ok": self.frames_ok,
            "bytes_ok": self.bytes_ok,
            "delimiters": self.delimiters,
            "buffered": len(self._buf),
            "frames_dropped": dict(self.frames_dropped),
            "bytes_dropped": dict(self.bytes_dropped),
        }
