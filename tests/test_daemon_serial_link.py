"""A serial link on a real pty: what a readable-yet-empty read means.

A pty's other side may flush the input queue between the moment the event loop saw the
line readable and the moment the link reads it (the emulated gateway drops what no host
read for a second). The read then returns nothing, as a hung-up line does; taken for a
disconnect, it cost a reconnect with its backoff and every frame meanwhile.
"""

from __future__ import annotations

import asyncio
import fcntl
import os
import struct
import termios
import time
import tty

from cellbridge.daemon.core.config import LinkConfig
from cellbridge.daemon.shell.links import SerialLink


def _queued(fd: int) -> int:
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


def _run(flush_between: bool, close_master: bool = False) -> tuple[list[bytes], list[tuple[bool, str]], SerialLink]:
    master, slave = os.openpty()
    tty.setraw(slave)
    data: list[bytes] = []
    states: list[tuple[bool, str]] = []
    link = SerialLink(LinkConfig("gw", os.ttyname(slave)), lambda name, b, t: data.append(b),
                      lambda name, up, why: states.append((up, why)))

    async def main() -> None:
        task = asyncio.create_task(link.run())
        loop = asyncio.get_running_loop()
        end = time.monotonic() + 10
        while not states and time.monotonic() < end:
            await asyncio.sleep(0.01)
        assert states == [(True, "")], states
        # One loop step writes and waits until the line holds the bytes; the callback it
        # schedules runs in the next step before the link's reader, which that step's
        # select found readable: the queue is flushed between readiness and read.
        done = loop.create_future()

        def flush() -> None:
            termios.tcflush(slave, termios.TCIFLUSH)
            done.set_result(None)

        def write() -> None:
            os.write(master, b"\x00first\x00")
            while _queued(slave) == 0 and time.monotonic() < end:
                time.sleep(0.001)
            if close_master:
                os.close(master)
                done.set_result(None)
            else:
                loop.call_soon(flush if flush_between else lambda: done.set_result(None))

        loop.call_soon(write)
        await done
        await asyncio.sleep(0.2)
        if not close_master:
            os.write(master, b"\x00second\x00")
            while b"second" not in b"".join(data) and time.monotonic() < end:
                await asyncio.sleep(0.01)
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass

    try:
        asyncio.run(main())
    finally:
        if not close_master:
            os.close(master)
        os.close(slave)
    return data, states, link


def test_a_line_flushed_between_readiness_and_read_stays_up() -> None:
    data, states, link = _run(flush_between=True)
    assert states == [(True, "")], states  # no "device lost", no reconnect
    assert b"".join(data) == b"\x00second\x00"
    assert link.stats()["empty_reads"] == 1


def test_a_line_read_without_a_flush_reads_everything() -> None:
    data, states, link = _run(flush_between=False)
    assert b"".join(data) == b"\x00first\x00\x00second\x00" and states == [(True, "")]
    assert link.stats()["empty_reads"] == 0


def test_a_hung_up_line_is_still_a_lost_device() -> None:
    data, states, link = _run(flush_between=False, close_master=True)
    assert states[0] == (True, "") and len(states) >= 2 and states[1][0] is False, states
    assert "device lost" in states[1][1], states
