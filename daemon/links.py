"""Link shells: one asyncio task per gateway line, feeding bytes and arrival times to a callback.

``SerialLink`` opens any pyserial URL (a tty, a pseudo-terminal, ``socket://host:port``)
and reads it from the event loop's reader callback, never blocking the loop: the port
is non-blocking (timeout 0), opening runs in a worker thread (a ``socket://`` connect
may take seconds). When the device goes away (USB pulled, pty closed, peer gone) the
link reports it and reopens with exponential backoff, forever: a robot's daemon must
outlive its cables. ``ReplayLink`` plays a capture file or an MCAP recording's serial
channel back as if it were a line.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Awaitable, Callable

import serial
import serial.serialposix

from cellbridge.daemon.capture import CaptureWriter
from cellbridge.daemon.replay_source import read_records
from cellbridge.daemon.config import LinkConfig

DataCallback = Callable[[str, bytes, float], None]
StateCallback = Callable[[str, bool, str], None]
READ_SIZE = 1 << 16


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
    def __init__(self, cfg: LinkConfig, on_data: DataCallback, on_state: StateCallback) -> None:
        super().__init__(cfg, on_data, on_state)
        self._ser: serial.SerialBase | None = None
        self.capture: CaptureWriter | None = None
        if cfg.capture:
            self.capture = CaptureWriter(cfg.capture)

    def _open(self) -> serial.SerialBase:
        # timeout=0: reads never wait; a socket:// write waits at most write_timeout
        return serial.serial_for_url(self.cfg.url, baudrate=self.cfg.baudrate, timeout=0, write_timeout=0.05)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        delay = self.cfg.reconnect_min
        try:
            while True:
                try:
                    ser = await loop.run_in_executor(None, self._open)
                except (serial.SerialException, OSError, ValueError) as exc:
                    self._on_state(self.name, False, f"open failed: {exc}")
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, self.cfg.reconnect_max)
                    continue
                delay = self.cfg.reconnect_min
                reason = await self._pump(loop, ser)
                self._on_state(self.name, False, reason)
                await asyncio.sleep(delay)
        finally:
            if self._ser is not None:
                self._close(loop)
            if self.capture is not None:
                self.capture.close()

    async def _pump(self, loop: asyncio.AbstractEventLoop, ser: serial.SerialBase) -> str:
        lost: asyncio.Future[str] = loop.create_future()
        fd = ser.fileno()
        capture = self.capture
        on_data, name = self._on_data, self.name

        read = _reader(ser)

        def readable() -> None:
            try:
                data = read()
            except (serial.SerialException, OSError) as exc:
                loop.remove_reader(fd)
                if not lost.done():
                    lost.set_result(f"device lost: {exc}")
                return
            if data:
                now = time.time()
                if capture is not None:
                    capture.write(now, data)
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
        try:
            ser.close()
        except (OSError, serial.SerialException):
            pass
        if self.capture is not None:
            self.capture.flush()

    def stats(self) -> dict[str, object]:
        out = super().stats()
        if self.capture is not None:
            out.update(self.capture.stats())
        return out

    def write(self, data: bytes) -> bool:
        ser = self._ser
        if ser is None:
            return super().write(data)
        try:
            if isinstance(ser, serial.serialposix.Serial):
                # A few dozen bytes: the driver's buffer takes them at once, or the line is
                # stuck and the command is dropped (counted) instead of stalling the loop.
                # A partial write is a dropped command too (the next frame's leading
                # delimiter resynchronises the bridge's decoder).
                return os.write(ser.fd, data) == len(data) or super().write(data)
            ser.write(data)
            return True
        except (serial.SerialException, OSError):
            return super().write(data)


def _reader(ser: serial.SerialBase) -> Callable[[], bytes]:
    """One non-blocking read of what is there. A tty or pty is read with a single
    ``os.read`` (pyserial's ``read`` polls around it, three system calls a read)."""
    if isinstance(ser, serial.serialposix.Serial):
        fd = ser.fd

        def read_fd() -> bytes:
            try:
                data = os.read(fd, READ_SIZE)
            except BlockingIOError:
                return b""
            except OSError as exc:
                raise serial.SerialException(f"read failed: {exc}") from None
            if not data:  # readable yet empty: the device is gone
                raise serial.SerialException("device disconnected")
            return data

        return read_fd
    return lambda: ser.read(READ_SIZE)


class ReplayLink(Link):
    """``replay:FILE``: the records of a capture at recorded speed × ``replay_speed`` (0: flat out).

    ``replay_clock = "recorded"`` feeds the recorded arrival times (golden tests:
    deterministic output); ``"shifted"`` moves them to start now.
    """

    def __init__(self, cfg: LinkConfig, on_data: DataCallback, on_state: StateCallback,
                 start_gate: Callable[[], Awaitable[None]] | None = None,
                 on_done: Callable[[str], None] | None = None) -> None:
        super().__init__(cfg, on_data, on_state)
        self.path = cfg.url.split(":", 1)[1]
        self._gate = start_gate
        self._on_done = on_done
        self.records = 0
        self.finished = False

    async def run(self) -> None:
        try:
            records = read_records(self.path, self.name)
            first = next(records, None)
        except (OSError, ValueError) as exc:
            self._on_state(self.name, False, f"replay failed: {exc}")
            return
        if self._gate is not None:
            await self._gate()
        self._on_state(self.name, True, "")
        speed, recorded = self.cfg.replay_speed, self.cfg.replay_clock == "recorded"
        start = time.time()
        why = "replay finished"
        if first is not None:
            t_first = first[0]
            try:
                for t, data in _chain(first, records):
                    rel = t - t_first
                    if speed > 0:
                        wait = start + rel / speed - time.time()
                        if wait > 0:
                            await asyncio.sleep(wait)
                    elif self.records % 64 == 0:
                        await asyncio.sleep(0)  # let sockets and control run between records
                    self.records += 1
                    self._on_data(self.name, data, t if recorded else start + (rel / speed if speed > 0 else rel))
            except (OSError, ValueError) as exc:  # a record further on is corrupt: the replay ends there
                why = f"replay failed after {self.records} records: {exc}"
        self.finished = True
        self._on_state(self.name, False, why)
        if self._on_done is not None:
            self._on_done(self.name)

    def stats(self) -> dict[str, object]:
        return {**super().stats(), "replayed_records": self.records, "replay_finished": self.finished}


def _chain(first: tuple[float, bytes], rest: object) -> object:
    yield first
    yield from rest  # type: ignore[misc]
