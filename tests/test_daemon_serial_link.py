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


def test_a_socket_line_whose_peer_hangs_up_is_lost_without_stalling_the_loop() -> None:
    """pyserial's socket:// ``close()`` sleeps 0.3 s ("give the server some time"): called on
    the event loop, each hang-up of a TCP gateway stopped every other link, the contact loop
    and control for 0.3 s (measured: the longest loop gap 0.30 s). The link is lost at once
    and the port closed off the loop."""
    import socket
    import threading

    from cellbridge.daemon.shell.links import open_serial

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    closed_on: list[threading.Thread] = []
    states: list[tuple[float, bool, str]] = []
    data: list[bytes] = []

    def opener(cfg: LinkConfig) -> object:
        ser = open_serial(cfg)
        close = ser.close

        def recorded_close() -> None:
            closed_on.append(threading.current_thread())
            close()

        ser.close = recorded_close  # type: ignore[method-assign]
        return ser

    link = SerialLink(LinkConfig("gw", f"socket://127.0.0.1:{port}", reconnect_min=5.0),
                      lambda name, b, t: data.append(b), lambda name, up, why: states.append((time.monotonic(), up, why)),
                      opener)  # type: ignore[arg-type]
    loop_thread: list[threading.Thread] = []

    async def main() -> None:
        loop_thread.append(threading.current_thread())
        task = asyncio.create_task(link.run())
        loop = asyncio.get_running_loop()
        conn, _ = await asyncio.wait_for(loop.run_in_executor(None, srv.accept), 10)
        try:
            end = time.monotonic() + 10
            while not states and time.monotonic() < end:
                await asyncio.sleep(0.01)
            conn.sendall(b"\x00abc\x00")
            while not data and time.monotonic() < end:
                await asyncio.sleep(0.01)
        finally:
            conn.close()
        while len(states) < 2 and time.monotonic() < end:
            await asyncio.sleep(0.01)
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass

    try:
        asyncio.run(main())
    finally:
        srv.close()
    assert data == [b"\x00abc\x00"]
    assert [s[1] for s in states] == [True, False] and "device lost" in states[1][2], states
    assert closed_on and loop_thread[0] not in closed_on, "the port was closed on the event loop's thread"
