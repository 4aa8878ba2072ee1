"""The recorder's core: daemon messages in, MCAP files out, rotated, nothing lost silently.

Fed ``(topic, msgpack payload, receive time)`` by a shell (``cellbridge record``), it
writes each as a JSON message (log time = the payload's ``t_host``, publish time = when
it was received, sequence = its ``seq``) into the current file, opens the next file when
the current one reaches ``rotate_bytes`` or ``rotate_seconds``, and finishes the chunk in
progress every ``chunk_seconds`` so a kill loses at most that much.

A message whose ``t_host`` is not a time an MCAP log time can hold (missing, not a
number, NaN, infinite, negative, past the year 2554) is recorded all the same, with its
receive time as log time, and counted in :attr:`bad_time`: a recorder that runs for days
goes on whatever one message says. A message over the bounds every reader applies
(:func:`cellbridge.recording.codec.check_size`) is not written and is counted in
:attr:`oversized`; a message on a topic the recorder was not asked for (a subscription is
a prefix) is counted with the :attr:`malformed` ones.

Messages the daemon published that never arrived (a subscriber's ZeroMQ queue is bounded;
a recorder that falls behind loses messages there) show as gaps in each topic's ``seq``,
counted per topic in :attr:`missed`; so do the first messages of a restarted daemon (its
``seq`` starts at 0 again, counted in :attr:`restarts`) published before the recorder
had reconnected.

A write that fails (disk full, I/O error) stops the recording: the error is kept in
:attr:`error`, the file keeps its whole chunks, later messages are counted in
:attr:`dropped`, and those of the chunk that could not be written in :attr:`unconfirmed`
(``recorded`` counts every message handed to the file, these included). It never raises into the shell: whatever happens to the disk, the
recorder says what and the daemon it listens to is untouched (it is another process).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cellbridge.recording import codec
from cellbridge.recording.mcapfile import RecordingWriter

Opener = Callable[[Path], RecordingWriter]

#: Log and publish times are unsigned 64-bit nanoseconds in MCAP.
MAX_NS = 2**64 - 1


def log_time_ns(t_host: Any) -> int | None:
    """``t_host`` (s since the epoch) as MCAP log time, or None if it cannot be one."""
    if isinstance(t_host, bool) or not isinstance(t_host, (int, float)):
        return None
    try:
        ns = int(t_host * 1e9)  # OverflowError for inf, ValueError for NaN
    except (OverflowError, ValueError):
        return None
    return ns if 0 < ns <= MAX_NS else None


def rotated_path(out: Path, index: int) -> Path:
    """``skin.mcap`` → ``skin-0000.mcap``, ``skin-0001.mcap``, ... (rotation on)."""
    return out.with_name(f"{out.stem}-{index:04d}{out.suffix or '.mcap'}")


class Recorder:
    def __init__(self, out: str | Path, opener: Opener, *, rotate_bytes: int = 0, rotate_seconds: float = 0.0,
                 chunk_seconds: float = 1.0, topics: set[str] | None = None) -> None:
        """``topics``: the only topics written (None: any); ``feed``'s ``now`` must not go back
        (the shell's clock is monotonic: rotation and chunk ages are measured on it)."""
        self.out = Path(out)
        self.topics = topics
        self._open = opener
        self.rotate_bytes = rotate_bytes
        self.rotate_seconds = rotate_seconds
        self.chunk_seconds = chunk_seconds
        self.writer: RecordingWriter | None = None
        self.files: list[Path] = []
        self._opened_at = 0.0
        self._flushed_at = 0.0
        self.recorded: Counter[str] = Counter()
        self.malformed = 0  # messages that were not [topic, msgpack map]: skipped, counted
        self.bad_time = 0  # messages whose t_host is no log time: written with the receive time as log time
        self.oversized = 0  # messages over the readers' bounds: not written
        self.dropped = 0  # messages received after the recording stopped on an error
        self.unconfirmed = 0  # messages in the chunk being built or written when a write failed: may be lost
        self.missed: Counter[str] = Counter()  # per topic: gaps in seq, messages that never reached us
        self._seq: dict[tuple[str, str], int] = {}  # (topic, source) -> last seq
        self._restarts: Counter[tuple[str, str]] = Counter()  # (topic, source) -> its seq going back
        self.error = ""

    @property
    def rotating(self) -> bool:
        return self.rotate_bytes > 0 or self.rotate_seconds > 0

    @property
    def stopped(self) -> bool:
        return bool(self.error)

    def _guard(self, op: Callable[[], Any]) -> bool:
        try:
            op()
            return True
        except OSError as exc:
            self._fail(exc)
            return False

    def _fail(self, exc: OSError) -> None:
        where = self.writer.path if self.writer is not None else self.out
        if self.writer is not None:
            self.unconfirmed = self.writer.pending
        self.error = f"{where}: {exc.strerror or exc}; recording stopped (the file keeps its whole chunks)"
        if self.writer is not None:
            try:
                self.writer.abandon()
            except OSError:
                pass
        self.writer = None

    def _next_file(self, now: float) -> bool:
        if self.writer is not None and not self._guard(self.writer.finish):
            return False
        path = rotated_path(self.out, len(self.files)) if self.rotating else self.out
        try:
            self.writer = self._open(path)
        except OSError as exc:
            self._fail(exc)
            return False
        self.files.append(path)
        self._opened_at = self._flushed_at = now
        return True

    def feed(self, topic: str, payload: bytes, now: float) -> None:
        """One message as received from the daemon at ``now`` (s since the epoch, on the shell's clock)."""
        if self.stopped:
            self.dropped += 1
            return
        if self.topics is not None and topic not in self.topics:
            self.malformed += 1
            return
        try:
            p = codec.from_msgpack(payload)
            data = codec.encode(topic, p)
        except (ValueError, TypeError, RecursionError):  # not msgpack, not a map, nested past the JSON encoder
            self.malformed += 1
            return
        try:
            codec.check_size(data)
        except codec.PayloadError:
            self.oversized += 1
            return
        w = self.writer
        if w is None or (self.rotate_bytes and w.size >= self.rotate_bytes) or \
                (self.rotate_seconds and now - self._opened_at >= self.rotate_seconds):
            if not self._next_file(now):
                self.dropped += 1
                return
            w = self.writer
        assert w is not None
        now_ns = min(max(int(now * 1e9), 0), MAX_NS)
        log_ns = log_time_ns(p.get("t_host"))
        if log_ns is None:
            self.bad_time += 1
            log_ns = now_ns
        seq = p.get("seq")
        if isinstance(seq, int):
            key = (topic, str(p.get("source", "")))
            last = self._seq.get(key)
            if last is not None and seq > last + 1:
                self.missed[topic] += seq - last - 1
            elif last is not None and seq <= last:  # the daemon restarted, numbering from 0: its first
                self.missed[topic] += seq  # messages, published before this recorder reconnected, never came
                self._restarts[key] += 1
            self._seq[key] = seq
        if self._guard(lambda: w.add(topic, data, log_ns, now_ns, seq if isinstance(seq, int) else 0)):
            self.recorded[topic] += 1
        else:
            self.dropped += 1
        self.tick(now)

    def tick(self, now: float) -> None:
        """Finish the chunk in progress if it is ``chunk_seconds`` old (call also when idle)."""
        if self.writer is not None and self.chunk_seconds > 0 and now - self._flushed_at >= self.chunk_seconds:
            self._flushed_at = now
            self._guard(self.writer.flush)

    def close(self) -> None:
        """Finish the current file (summary and index): a viewer opens it at once."""
        if self.writer is not None:
            w, self.writer = self.writer, None
            try:
                w.finish()
            except OSError as exc:
                self.writer = w
                self._fail(exc)

    @property
    def restarts(self) -> int:
        """Daemon restarts seen (a topic's seq going back; each daemon's counted once per restart)."""
        per_source: dict[str, int] = {}
        for (_, source), n in self._restarts.items():
            per_source[source] = max(per_source.get(source, 0), n)
        return sum(per_source.values())

    def stats(self) -> dict[str, Any]:
        return {"recorded": dict(self.recorded), "messages": sum(self.recorded.values()),
                "malformed": self.malformed, "bad_time": self.bad_time, "oversized": self.oversized,
                "dropped": self.dropped, "unconfirmed": self.unconfirmed,
                "missed": dict(self.missed), "restarts": self.restarts, "files": [str(f) for f in self.files],
                "error": self.error}
