"""Serial-line framing: COBS-encoded frames separated by 0x00.

COBS removes every zero byte from a frame, so 0x00 marks frame boundaries
unambiguously: after any corruption the decoder loses at most the frame in
progress and is back in step at the next delimiter. The encoder writes a
delimiter *before* and after each frame so a receiver that joins mid-stream (or
after line noise) discards only the garbage up to the first delimiter.
"""

from __future__ import annotations

from collections import Counter

from cobs import cobs

from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.frame import MAX_FRAME, Frame, decode, encode

DELIMITER = b"\x00"


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
    delivered frames. Every byte fed is accounted for:
    ``bytes_in == bytes_ok + sum(bytes_dropped) + delimiters + buffered``.

    Causes: ``overlong`` (more bytes than any valid frame before a delimiter),
    ``cobs`` (invalid COBS), and the :class:`ProtocolError` causes of
    :func:`decode` (``crc``, ``short``, ``version``, ...).
    """

    def __init__(self, max_frame: int = MAX_FRAME) -> None:
        self.max_buffer = max_encoded_len(max_frame)
        self._buf = bytearray()
        self._skipping = False  # inside an over-long run: discard until the next delimiter
        self.frames_ok = 0
        self.bytes_ok = 0  # COBS bytes of delivered frames
        self.bytes_in = 0
        self.frames_dropped: Counter[str] = Counter()
        self.bytes_dropped: Counter[str] = Counter()

    @property
    def buffered(self) -> int:
        """Bytes held for the frame in progress (at most ``max_buffer``)."""
        return len(self._buf)

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Frame]:
        self.bytes_in += len(chunk)
        parts = bytes(chunk).split(DELIMITER)
        frames: list[Frame] = []
        # Every part but the last ended at a delimiter; the last is the frame in progress.
        for i, part in enumerate(parts):
            last = i == len(parts) - 1
            if self._skipping:
                self.bytes_dropped["overlong"] += len(part)
                if not last:
                    self._skipping = False
                continue
            if self._buf:
                self._buf += part
                if not last:
                    part, self._buf = bytes(self._buf), bytearray()
            elif last:
                self._buf += part
            if last:
                if len(self._buf) > self.max_buffer:
                    self._drop_overlong()
                break
            if part:
                self._frame(part, frames)
        return frames

    def _drop_overlong(self) -> None:
        self.bytes_dropped["overlong"] += len(self._buf)
        self.frames_dropped["overlong"] += 1
        self._buf = bytearray()
        self._skipping = True

    def _frame(self, encoded: bytes, out: list[Frame]) -> None:
        if len(encoded) > self.max_buffer:
            self.bytes_dropped["overlong"] += len(encoded)
            self.frames_dropped["overlong"] += 1
            return
        try:
            out.append(decode(cobs.decode(encoded)))
        except cobs.DecodeError:
            self.bytes_dropped["cobs"] += len(encoded)
            self.frames_dropped["cobs"] += 1
            return
        except ProtocolError as exc:
            self.bytes_dropped[exc.cause] += len(encoded)
            self.frames_dropped[exc.cause] += 1
            return
        self.frames_ok += 1
        self.bytes_ok += len(encoded)

    def counters(self) -> dict[str, object]:
        """A snapshot for health reports: totals and drops by cause."""
        return {
            "bytes_in": self.bytes_in,
            "frames_ok": self.frames_ok,
            "bytes_ok": self.bytes_ok,
            "frames_dropped": dict(self.frames_dropped),
            "bytes_dropped": dict(self.bytes_dropped),
        }
