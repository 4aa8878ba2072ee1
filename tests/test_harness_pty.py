"""The tests' pty (daemon_harness.Pty) fails a test whose daemon stopped reading, instead
of blocking it for ever once the line's buffer is full."""

from __future__ import annotations

import os
import threading
import time
import tty
from pathlib import Path

import pytest

from daemon_harness import Pty


def test_a_write_nobody_reads_fails_at_its_limit(tmp_path: Path) -> None:
    """The line open in raw mode (as the daemon holds it) and not read: a pty holds a few
    KB, then a blocking write waited for ever."""
    pty = Pty(tmp_path / "gw")
    fd = os.open(pty.link, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    try:
        t0 = time.monotonic()
        with pytest.raises(AssertionError, match="nobody read the pty"):
            pty.write(b"\x00" * 200_000, limit=0.5)
        assert time.monotonic() - t0 < 5.0
    finally:
        os.close(fd)
        pty.close()


def test_a_write_a_reader_takes_arrives_whole(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gw")
    fd = os.open(pty.link, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    got = bytearray()
    data = bytes(range(256)) * 400  # 100 KB: many times what the line holds

    def read() -> None:
        while len(got) < len(data):
            got.extend(os.read(fd, 65536))

    th = threading.Thread(target=read, daemon=True)
    th.start()
    try:
        pty.write(data)
        th.join(10.0)
        assert bytes(got) == data
    finally:
        os.close(fd)
        pty.close()
