"""Fakes for the daemon's shells, so links, the service and the contact worker run
in-process in milliseconds (bellows' ``FakeTransport`` family is the model).

- :class:`FakeDevice`: a gateway's serial device that can be unplugged and replugged;
  its :meth:`~FakeDevice.open` is a ``SerialLink`` opener. The port it opens is a real
  pipe, so the event loop's reader callback sees it exactly as a tty; it hands the
  link ``chunk`` bytes a read (1: one byte at a time) and loses each byte with
  probability ``loss`` (deterministic by ``seed``).
- :class:`FakeClock`: host time that only moves when a link sleeps; every sleep recorded.
- :class:`ScriptedExecutor`: answers the first ``answers`` jobs inline, then hangs (its
  futures never complete) — a contact worker stuck in an estimate.
- :class:`RecordingHooks`: the service's systemd hooks, recording what it said.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.process
import os
import random
import time
from collections.abc import Callable
from typing import Any

import serial
from cellbridge.daemon.core.config import Config, LinkConfig
from cellbridge.daemon.ops.ops import OpsHooks


class FakeSerial:
    """One opening of a :class:`FakeDevice` (what pyserial's ``Serial`` is to a tty)."""

    def __init__(self, device: FakeDevice) -> None:
        self.device = device
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        self.closed = False
        self.gone = False
        self.reads: list[int] = []  # size of each non-empty read

    def fileno(self) -> int:
        return self._r

    def read(self, size: int = 1) -> bytes:
        if self.closed:
            raise serial.SerialException("port is closed")
        try:
            data = os.read(self._r, min(size, self.device.chunk))
        except BlockingIOError:
            return b""
        if not data:  # the write end is closed: unplugged
            raise serial.SerialException("device disconnected")
        self.reads.append(len(data))
        return data

    def write(self, data: bytes) -> int:
        if self.gone:
            raise serial.SerialException("write failed: device disconnected")
        self.device.written += data
        return len(data)

    def _deliver(self, data: bytes) -> None:
        if not self.gone:
            os.write(self._w, data)

    def _hang_up(self) -> None:
        if not self.gone:
            self.gone = True
            os.close(self._w)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._hang_up()
            os.close(self._r)


class FakeDevice:
    def __init__(self, chunk: int = 1 << 16, loss: float = 0.0, seed: int = 0) -> None:
        self.chunk = chunk
        self.loss = loss
        self._rng = random.Random(seed)
        self.plugged = True
        self.port: FakeSerial | None = None
        self.opens = 0
        self.failed_opens = 0
        self.written = bytearray()  # what the host wrote (commands)
        self.lost = 0

    def open(self, cfg: LinkConfig) -> FakeSerial:
        """A ``SerialLink`` opener: fails like a missing /dev/ttyUSB0 while unplugged."""
        if not self.plugged:
            self.failed_opens += 1
            raise serial.SerialException(f"could not open port {cfg.url}: No such file or directory")
        self.opens += 1
        self.port = FakeSerial(self)
        return self.port

    def send(self, data: bytes) -> None:
        """The gateway writes ``data`` to the host (bytes lost on the way are counted)."""
        if self.loss:
            kept = bytes(b for b in data if self._rng.random() >= self.loss)
            self.lost += len(data) - len(kept)
            data = kept
        if self.port is not None and data:
            self.port._deliver(data)

    def unplug(self) -> None:
        self.plugged = False
        if self.port is not None:
            self.port._hang_up()

    def replug(self) -> None:
        self.plugged = True


class FakeClock:
    """Host time for a link: it stands still except when a sleep moves it on."""

    def __init__(self, t: float = 1_700_000_000.0) -> None:
        self.t = t
        self.wall_offset = 0.0  # wall-clock minus monotonic time: a test steps the wall clock here
        self.sleeps: list[float] = []

    def time(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.t + self.wall_offset

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds
        await asyncio.sleep(0)


class ScriptedExecutor(concurrent.futures.Executor):
    """Runs the first ``answers`` jobs inline; every later job hangs until the executor is killed."""

    made: list[ScriptedExecutor] = []

    def __init__(self, answers: int) -> None:
        self.answers = answers
        self.jobs = 0
        self.hung: list[concurrent.futures.Future[Any]] = []
        self.killed = False
        self.shutdowns: list[bool] = []  # wait= of each shutdown

    @classmethod
    def factory(cls, answers: int) -> Callable[[], ScriptedExecutor]:
        """An executor factory for a ContactWorker; every executor made is in ``made``."""
        cls.made = []

        def make() -> ScriptedExecutor:
            ex = cls(answers)
            cls.made.append(ex)
            return ex

        return make

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        if fn.__name__ == "warm_up":
            fut.set_result(None)
            return fut
        self.jobs += 1
        if self.jobs <= self.answers:
            fut.set_result(fn(*args, **kwargs))
        else:
            fut.set_running_or_notify_cancel()  # running: cancelling it cannot end it
            self.hung.append(fut)
        return fut

    def kill(self) -> None:
        self.killed = True
        for fut in self.hung:
            if not fut.done():
                fut.set_exception(concurrent.futures.process.BrokenProcessPool("killed"))

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.shutdowns.append(wait)
        if wait and any(not f.done() for f in self.hung):
            raise AssertionError("shutdown(wait=True) on a hung worker would wait for ever")


class RecordingHooks(OpsHooks):
    """The real hooks without systemd, recording each notification."""

    def __init__(self, config: Config) -> None:
        super().__init__(config, env={})
        self.said: list[tuple[str, str]] = []

    def ready(self, status: str) -> None:
        self.said.append(("ready", status))

    def stopping(self) -> None:
        self.said.append(("stopping", ""))

    def reloading(self) -> None:
        self.said.append(("reloading", ""))


async def until(cond: Callable[[], bool], limit: float = 30.0) -> None:
    """Run the loop until ``cond()`` holds; a guard against a hang, not a speed check."""
    loop = asyncio.get_running_loop()
    end = loop.time() + limit
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached")
        await asyncio.sleep(0.001)


class SlowStartExecutor(concurrent.futures.ThreadPoolExecutor):
    """One worker thread whose warm-up takes ``delay`` s: a worker process on a fresh
    installation, compiling the estimator's kernels before its first estimate."""

    def __init__(self, delay: float) -> None:
        super().__init__(1)
        self.delay = delay

    @classmethod
    def factory(cls, delay: float) -> Callable[[], SlowStartExecutor]:
        return lambda: cls(delay)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        if fn.__name__ == "warm_up":
            delay = self.delay

            def slow(*a: Any, **kw: Any) -> Any:
                time.sleep(delay)
                return fn(*a, **kw)

            return super().submit(slow, *args, **kwargs)
        return super().submit(fn, *args, **kwargs)
