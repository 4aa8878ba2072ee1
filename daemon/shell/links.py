"""Link shells: one asyncio task per gateway line, feeding bytes and arrival times to a callback.

``SerialLink`` opens any pyserial URL (a tty, a pseudo-terminal, ``socket://host:port``)
and reads it from the event loop's reader callback, never blocking the loop: the port
is non-blocking (timeout 0), opening runs in a worker thread (a ``socket://`` connect
may take seconds). When the device goes away (USB pulled, pty closed, peer gone) the
link reports it and reopens with exponential backoff, forever: a robot's daemon must
outlive its cables. ``ReplayLink`` plays a capture file or an MCAP recording's serial
channel back as if it were a line.

A ``SerialLink`` takes its device from an *opener* and its time and waits from a
:class:`Clock`, so tests run it on a fake device and a fake clock: unplugged and
replugged, bytes one at a time or lost, backoff without waiting it out.
"""

from __future__ import annotations

import asyncio
import heapq
import math
import os
import termios
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Protocol

import serial
import serial.serialposix
from cellbridge.daemon.core.config import LinkConfig
from cellbridge.daemon.shell.capture import CaptureWriter
from cellbridge.daemon.shell.replay_source import read_records

DataCallback = Callable[[str, bytes, float], None]
StateCallback = Callable[[str, bool, str], None]
READ_SIZE = 1 << 16


class Port(Protocol):
    """What a link needs of an open device (a pyserial port, or a test's fake): a file
    descriptor that polls readable when there is data or the device is gone, and
    non-blocking reads (``b""``: nothing now) and writes. Reads and writes raise
    :class:`serial.SerialException` (or OSError) once the device is gone."""

    def fileno(self) -> int: ...
    def read(self, size: int = 1) -> bytes: ...
    def write(self, data: bytes) -> int | None: ...
    def close(self) -> None: ...


#: Opens the device of a link's configuration; raises SerialException, OSError or ValueError.
Opener = Callable[[LinkConfig], Port]


def open_serial(cfg: LinkConfig) -> Port:
    """Any pyserial URL. timeout=0: reads never wait; a socket:// write waits at most write_timeout."""
    return serial.serial_for_url(cfg.url, baudrate=cfg.baudrate, timeout=0, write_timeout=0.05)


class Clock(Protocol):
    """Where a shell reads the host time and waits. ``time`` is the pipeline's time base
    (monotonic: a wall-clock step must not move it); ``wall`` is for what is kept on disk."""

    def time(self) -> float: ...
    def wall(self) -> float: ...
    async def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """The host's monotonic clock, its wall clock and the event loop's timers."""

    def time(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)


SYSTEM_CLOCK = SystemClock()


class Link:
    """What the service sees of a link."""

    def __init__(self, cfg: LinkConfig, on_data: DataCallback, on_state: StateCallback) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self._on_data = on_data
        self._on_state = on_state
        self.writes_dropped = 0  # commands for a link that is down (or a replay)

    async def run(self) -> None:
        raise NotImplementedError

    def write(self, data: bytes) -> bool:
        self.writes_dropped += 1
        return False

    def stats(self) -> dict[str, object]:
        return {"writes_dropped": self.writes_dropped}


class SerialLink(Link):
    """A gateway's serial line: reads go to ``on_data(name, bytes, host time)``, state
    changes to ``on_state(name, up, why)``; reopened with exponential backoff
    (``reconnect_min`` doubling to ``reconnect_max``, back to the minimum after a
    successful open) until the task is cancelled."""

    def __init__(self, cfg: LinkConfig, on_data: DataCallback, on_state: StateCallback,
                 opener: Opener = open_serial, clock: Clock = SYSTEM_CLOCK) -> None:
        super().__init__(cfg, on_data, on_state)
        self._opener = opener
        self._clock = clock
        self._ser: Port | None = None
        self.capture: CaptureWriter | None = None
        if cfg.capture:
            self.capture = CaptureWriter(cfg.capture)
        # A capture's times are the wall clock's at its start, then the monotonic clock's: a
        # replay in recorded time takes them as its one time base, which a wall-clock step
        # (NTP) must not move (replayed, a step back stopped every contact estimate).
        self._capture_offset = clock.wall() - clock.time()
        self.empty_reads = 0  # readable, then nothing to read, the line still there (a flush between)

    def _empty_read(self) -> None:
        self.empty_reads += 1

    def _open(self) -> Port:
        return self._opener(self.cfg)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        delay = self.cfg.reconnect_min
        try:
            while True:
                try:
                    ser = await loop.run_in_executor(None, self._open)
                except (serial.SerialException, OSError, ValueError) as exc:
                    self._on_state(self.name, False, f"open failed: {exc}")
                    await self._clock.sleep(delay)
                    delay = min(delay * 2, self.cfg.reconnect_max)
                    continue
                delay = self.cfg.reconnect_min
                reason = await self._pump(loop, ser)
                self._on_state(self.name, False, reason)
                await self._clock.sleep(delay)
        finally:
            if self._ser is not None:
                self._close(loop)
            if self.capture is not None:
                self.capture.close()

    async def _pump(self, loop: asyncio.AbstractEventLoop, ser: Port) -> str:
        lost: asyncio.Future[str] = loop.create_future()
        fd = ser.fileno()
        capture = self.capture
        on_data, name, clock = self._on_data, self.name, self._clock

        read = _reader(ser, self._empty_read)

        def readable() -> None:
            try:
                data = read()
            except (serial.SerialException, OSError) as exc:
                loop.remove_reader(fd)
                if not lost.done():
                    lost.set_result(f"device lost: {exc}")
                return
            if data:
                now = clock.time()  # the pipeline's time base
                if capture is not None:
                    capture.write(now + self._capture_offset, data)
                on_data(name, data, now)

        self._ser = ser
        self._on_state(self.name, True, "")
        loop.add_reader(fd, readable)
        try:
            return await lost
        finally:
            self._close(loop)

    def _close(self, loop: asyncio.AbstractEventLoop) -> None:
        ser, self._ser = self._ser, None
        if ser is None:
            return
        try:
            loop.remove_reader(ser.fileno())
        except (OSError, ValueError, serial.SerialException):
            pass
        # Off the loop: pyserial's socket:// close sleeps 0.3 s, and a tty's close may wait
        # for its output to drain; on the loop, every other link, the contact loop and
        # control stood still meanwhile, at each hang-up of a TCP gateway.
        try:
            loop.run_in_executor(None, _close_port, ser)
        except RuntimeError:  # the loop's executor is shut down (the process is ending)
            _close_port(ser)
        if self.capture is not None:
            self.capture.flush()

    def stats(self) -> dict[str, object]:
        out = super().stats()
        out["empty_reads"] = self.empty_reads
        if self.capture is not None:
            out.update(self.capture.stats())
        return out

    def write(self, data: bytes) -> bool:
        ser = self._ser
        if ser is None:
            return super().write(data)
        try:
            if isinstance(ser, serial.serialposix.Serial) and ser.fd is not None:
                # A few dozen bytes: the driver's buffer takes them at once, or the line is
                # stuck and the command is dropped (counted) instead of stalling the loop.
                # A partial write is a dropped command too (the next frame's leading
                # delimiter resynchronises the bridge's decoder).
                return os.write(ser.fd, data) == len(data) or super().write(data)
            ser.write(data)
            return True
        except (serial.SerialException, OSError):
            return super().write(data)


def _close_port(ser: Port) -> None:
    try:
        ser.close()
    except (OSError, serial.SerialException):
        pass


#: Readable-yet-empty reads in a row, the line still answering, after which it counts as gone
#: (a driver that reports readiness it never backs with data would otherwise spin the loop).
EMPTY_READS_GONE = 1000


def _reader(ser: Port, on_empty: Callable[[], None]) -> Callable[[], bytes]:
    """One non-blocking read of what is there. A tty or pty is read with a single
    ``os.read`` (pyserial's ``read`` polls around it, three system calls a read).

    A read that finds nothing although the line was readable is a line gone (a hung-up
    tty) only if the line no longer answers: the input queue may have been flushed in
    between (a pty's other side drops what was not read for a while), and taking that for
    a disconnect cost a reconnect with its backoff. Such a read calls ``on_empty``."""
    fd = ser.fd if isinstance(ser, serial.serialposix.Serial) else None
    if fd is not None:
        empty = 0

        def read_fd() -> bytes:
            nonlocal empty
            try:
                data = os.read(fd, READ_SIZE)
            except BlockingIOError:
                return b""
            except OSError as exc:
                raise serial.SerialException(f"read failed: {exc}") from None
            if data:
                empty = 0
                return data
            try:
                termios.tcgetattr(fd)  # a hung-up tty answers EIO
            except (termios.error, OSError):
                raise serial.SerialException("device disconnected") from None
            empty += 1
            if empty >= EMPTY_READS_GONE:
                raise serial.SerialException(f"device disconnected ({empty} empty reads in a row)")
            on_empty()
            return b""

        return read_fd
    return lambda: ser.read(READ_SIZE)


class RecordedOrder:
    """The replays of one service in recorded time, fed as one recording: paced from one
    origin (the earliest first record of them all, at the time every link has its first
    record) and in one time order across links (a link waits while another's next record
    is older than its own).

    Paced each from its own first record, a gateway whose line came up later was replayed
    as if it came up with the others: its records ran ahead of the others' by that much,
    the service's recorded clock with them, and the others' bridges looked silent while
    their reads were still to come. Flat out, each link fed 64 records at a turn: a quiet
    line's 64 cover more recorded time than a busy one's, and drifted ahead without bound."""

    def __init__(self, names: list[str]) -> None:
        self._next: dict[str, float | None] = dict.fromkeys(names)  # None: not yet known
        self._changed = asyncio.Event()
        self.origin: tuple[float, float] | None = None  # (recorded time, host time) of the start

    def post(self, name: str, t: float) -> None:
        """``name``'s next record is at recorded time ``t`` (inf: it has no more)."""
        self._next[name] = t
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    async def start(self, name: str, t: float, now: Callable[[], float]) -> tuple[float, float]:
        """``name``'s first record is at ``t`` (inf: none); waits for every link's, then the
        (recorded, host) times the replays are paced from (host time: ``now()`` then)."""
        self.post(name, t)
        while any(v is None for v in self._next.values()):
            await self._changed.wait()
        if self.origin is None:
            first = min(v for v in self._next.values() if v is not None)
            self.origin = (first if math.isfinite(first) else t, now())
        return self.origin

    async def turn(self, name: str, t: float) -> None:
        """Wait until no other link's next record comes before ``t``, ``name``'s next (posted):
        older, or as old on a link whose name sorts first (reads of one time, as the offline
        driver orders them: a tie taken in whichever order the tasks ran changed which
        frame each element stage saw first)."""
        while True:
            if all((t, name) <= (math.inf if v is None else v, k) for k, v in self._next.items() if k != name):
                return
            await self._changed.wait()


class ReplayPacer:
    """The service's replays at a recorded speed on shifted time, fed by one task: each
    record at its due time, and the records of every line due within :attr:`window` s of
    the first of them at one wake, stamped each with its own due time.

    Fed each by its own task, the lines' records cost a timer, a future and a task's wake
    apiece: a skin of 22 gateways at 100 Hz, 2 200 records a second, spent about as much on
    the waking as on the records' decoding. The gateways' records of one frame come within
    a fraction of a millisecond of each other; one wake takes them all. A record is fed at
    most ``window`` after its due time (its stamp is its due time: :attr:`ReplayLink.LATE`
    is far larger), in the order of their due times across the lines (ties: the line that
    joined first).

    :meth:`join` is a line's whole replay once its gate has opened; the feeding task runs
    while some line has records left (a line that joins while it sleeps for later records
    wakes it). The pacing waits on the ``clock`` of the lines (a test's fake clock)."""

    #: s of records taken at one wake after the first due (a fraction of a period at 100 Hz)
    WINDOW = 0.0003
    #: records fed in a row behind schedule before the loop's other tasks run (ticks, looks)
    YIELD_EVERY = 64

    def __init__(self, clock: Clock = SYSTEM_CLOCK, window: float = WINDOW) -> None:
        self._clock = clock
        self.window = window
        self._heap: list[tuple[float, int, _PacedLine]] = []
        self._seq = 0
        self._driver: asyncio.Task[None] | None = None
        self._target = math.inf  # when the sleeping driver wakes
        self._lines = 0  # lines joined and not left
        self.wakes = 0  # the driver's wakes that fed records (for tests and benchmarks)

    async def join(self, line: _PacedLine) -> None:
        """Feed ``line``'s records until it has none left (or its reading failed: its
        ``why``); cancelled, the line leaves and the others go on."""
        done = asyncio.get_running_loop().create_future()
        line.done = done
        self._lines += 1
        try:
            self._push(line)
            await done
        finally:
            line.left = True
            if not done.done():
                done.cancel()
            self._lines -= 1
            if not self._lines and self._driver is not None:  # (the last line left: no task stays behind)
                self._driver.cancel()
                self._driver = None

    def _push(self, line: _PacedLine) -> None:
        due = line.due
        heapq.heappush(self._heap, (due, self._seq, line))
        self._seq += 1
        driver = self._driver
        if driver is None or driver.done():
            self._driver = asyncio.get_running_loop().create_task(self._drive(), name="replay pacer")
        elif due + self.window < self._target:  # sooner than the sleeping driver wakes: wake it now
            driver.cancel()
            self._driver = asyncio.get_running_loop().create_task(self._drive(), name="replay pacer")

    async def _drive(self) -> None:
        heap, clock = self._heap, self._clock
        unyielded = 0
        while heap:
            first = heap[0][0]
            if first - clock.time() > 0:
                # the latest record due within the window of the first: one wake for them all
                target = max(d for d, _, _ in heap if d <= first + self.window)
                self._target = target
                await clock.sleep(target - clock.time())
                self._target = math.inf
                unyielded = 0
            elif unyielded >= self.YIELD_EVERY:  # behind: the loop's other tasks run now and then
                await asyncio.sleep(0)
                unyielded = 0
            now = clock.time()
            fed = False
            while heap and heap[0][0] <= now:
                due, _, line = heapq.heappop(heap)
                if line.left:
                    continue
                unyielded += 1
                fed = True
                try:
                    more = line.feed(due)
                except Exception as exc:  # the line's own failure: its task raises it, the others go on
                    line.left = True
                    if line.done is not None and not line.done.done():
                        line.done.set_exception(exc)
                    continue
                if more:
                    heapq.heappush(heap, (line.due, self._seq, line))
                    self._seq += 1
                elif line.done is not None and not line.done.done():
                    line.done.set_result(None)
            self.wakes += fed


class _PacedLine:
    """One replay's place in a :class:`ReplayPacer`: its next record and due time, fed by
    its link's :meth:`ReplayLink._replay_paced`."""

    __slots__ = ("feed", "due", "done", "left")

    def __init__(self, feed: Callable[[float], bool], due: float) -> None:
        self.feed = feed  # (its due time) -> whether the line has a next record (then self.due)
        self.due = due
        self.done: asyncio.Future[None] | None = None
        self.left = False


class ReplayLink(Link):
    """``replay:FILE``: the records of a capture at recorded speed × ``replay_speed`` (0: flat out).

    ``replay_clock = "recorded"`` feeds the recorded arrival times (golden tests:
    deterministic output); ``"shifted"`` moves them to start now.

    A shifted replay paced at a speed that feeds a record more than :attr:`LATE` after its
    due time (a starved loop) stamps it when it feeds it, as a line's read is stamped when
    it is read, and goes on with its schedule: the records due meanwhile come in a burst,
    as a line's bytes do after the kernel held them. Stamped on schedule instead, such a
    record came into a pipeline whose looks and ticks had already run at the later time:
    its time went backwards, the element stage skipped steps, and a re-run took its
    baselines from other readings than the recorded run (9 fF apart, on a loaded machine).
    Counted in ``replay_late`` (records stamped after their due time) and ``replay_late_max`` (s).
    A replay behind its schedule lets the loop's other tasks run every 64 records (ticks,
    estimates, the watchdog); a recording whose times step back (captures appended) is paced on from the step,
as if it went on there.
    """

    #: s a paced record may be fed after its due time and still carry it (a sleep's wake-up)
    LATE = 0.005

    def __init__(self, cfg: LinkConfig, on_data: DataCallback, on_state: StateCallback,
                 start_gate: Callable[[], Awaitable[None]] | None = None,
                 on_done: Callable[[str], None] | None = None, clock: Clock = SYSTEM_CLOCK,
                 order: RecordedOrder | None = None, pacer: ReplayPacer | None = None) -> None:
        super().__init__(cfg, on_data, on_state)
        self._order = order  # the service's replays in recorded time, fed as one (recorded clock only)
        self._pacer = pacer  # the service's shifted replays at a recorded speed, fed by one task
        self.path = cfg.url.split(":", 1)[1]
        self._clock = clock  # paces a shifted replay (its time and its sleeps): a test's runs in fake time
        self._gate = start_gate
        self._on_done = on_done
        self.records = 0
        self.finished = False
        self.late = 0  # records a shifted replay fed more than LATE after they were due
        self.late_max = 0.0  # s, the latest of them

    async def run(self) -> None:
        try:
            records = read_records(self.path, self.name)
            first = next(records, None)
        except (OSError, ValueError) as exc:
            self._on_state(self.name, False, f"replay failed: {exc}")
            if self._order is not None:
                self._order.post(self.name, math.inf)
            return
        order = self._order
        try:
            await self._replay(first, records)
        finally:  # (also cancelled or failed: the other links must not wait for this one)
            if order is not None:
                order.post(self.name, math.inf)

    async def _replay(self, first: tuple[float, bytes] | None, records: Iterator[tuple[float, bytes]]) -> None:
        order = self._order
        if self._gate is not None:
            await self._gate()
        self._on_state(self.name, True, "")
        speed, recorded = self.cfg.replay_speed, self.cfg.replay_clock == "recorded"
        clock = self._clock
        start = clock.time()  # shifted: records replayed on the pipeline's (monotonic) time base
        why = "replay finished"
        if order is not None:  # one origin for the service's replays in recorded time
            t_first, start = await order.start(self.name, math.inf if first is None else first[0], clock.time)
        elif first is not None:
            t_first = first[0]
        if first is not None and self._pacer is not None and speed > 0 and order is None and not recorded:
            why = await self._replay_paced(self._pacer, first, records, t_first, start, speed)
        elif first is not None:
            last, ahead, unyielded = -math.inf, 0.0, 0
            prev, back = -math.inf, 0.0  # the recording's last time; s it stepped back in all
            try:
                for t, data in _chain(first, records):
                    if order is not None:
                        order.post(self.name, t)  # (before a sleep: the others need not wait for it)
                    if t < prev:  # the recording steps back (captures appended): paced on from
                        back += prev - t  # there, not fed at once (a day's capture in a burst)
                    prev = t
                    rel = t - t_first + back
                    if speed > 0:
                        ahead = max(ahead, rel)
                        due = stamp = start + ahead / speed
                        wait = due - clock.time()
                        if wait > 0:
                            await clock.sleep(wait)
                            unyielded = 0
                            wait = due - clock.time()  # the sleep itself may end late (a busy loop)
                        elif unyielded >= 64:  # behind: the loop's other tasks run now and then
                            await asyncio.sleep(0)
                            unyielded = 0
                            wait = due - clock.time()
                        unyielded += 1
                        if wait < -self.LATE:
                            stamp = due - wait
                        stamp = max(stamp, last)  # one on time behind a late one: not before it
                        last = stamp
                        if stamp > due and not recorded:
                            self.late += 1
                            self.late_max = max(self.late_max, stamp - due)
                    else:
                        stamp = start + rel
                        if self.records % 64 == 0:
                            await asyncio.sleep(0)  # let sockets and control run between records
                    if order is not None:
                        await order.turn(self.name, t)
                    self.records += 1
                    self._on_data(self.name, data, t if recorded else stamp)
            except (OSError, ValueError) as exc:  # a record further on is corrupt: the replay ends there
                why = f"replay failed after {self.records} records: {exc}"
        self.finished = True
        self._on_state(self.name, False, why)
        if self._on_done is not None:
            self._on_done(self.name)

    async def _replay_paced(self, pacer: ReplayPacer, first: tuple[float, bytes],
                            records: Iterator[tuple[float, bytes]], t_first: float, start: float,
                            speed: float) -> str:
        """The records from ``first`` on, fed by ``pacer`` at ``speed`` × recorded speed on
        shifted time: paced and stamped as the replay's own loop does (a record fed more than
        :attr:`LATE` after its due time is stamped when it is fed; a recording that steps back
        is paced on from the step). Why the replay ended."""
        clock, name, on_data = self._clock, self.name, self._on_data
        it = _chain(first, records)
        prev, back, ahead, last = -math.inf, 0.0, 0.0, -math.inf
        why = "replay finished"

        def due_of(t: float) -> float:
            nonlocal prev, back, ahead
            if t < prev:  # the recording steps back (captures appended): paced on from there
                back += prev - t
            prev = t
            ahead = max(ahead, t - t_first + back)
            return start + ahead / speed

        data = first[1]

        def feed(due: float) -> bool:
            nonlocal last, data, why
            wait = due - clock.time()
            stamp = due if wait >= -self.LATE else due - wait
            stamp = max(stamp, last)  # one on time behind a late one: not before it
            last = stamp
            if stamp > due:
                self.late += 1
                self.late_max = max(self.late_max, stamp - due)
            self.records += 1
            on_data(name, data, stamp)
            try:
                got = next(it, None)
            except (OSError, ValueError) as exc:  # a record further on is corrupt: the replay ends there
                why = f"replay failed after {self.records} records: {exc}"
                return False
            if got is None:
                return False
            line.due = due_of(got[0])
            data = got[1]
            return True

        next(it)  # (first: its due below)
        line = _PacedLine(feed, due_of(first[0]))
        await pacer.join(line)
        return why

    def stats(self) -> dict[str, object]:
        return {**super().stats(), "replayed_records": self.records, "replay_finished": self.finished,
                "replay_late": self.late, "replay_late_max": self.late_max}


def _chain(first: tuple[float, bytes], rest: Iterator[tuple[float, bytes]]) -> Iterator[tuple[float, bytes]]:
    yield first
    yield from rest
