"""`mesh up --pty-link DIR`: a stable name for each gateway's pty, whose /dev/pts number changes."""

from __future__ import annotations

import os
from pathlib import Path

from cellbridge.emulator.realtime.pty_link import link_gateway


def test_the_link_follows_the_current_pty(tmp_path: Path) -> None:
    first_master, first_slave = os.openpty()
    second_master, second_slave = os.openpty()
    try:
        link = link_gateway(tmp_path, 1, os.ttyname(first_slave))
        assert link == tmp_path / "gateway-1" and os.readlink(link) == os.ttyname(first_slave)
        link_gateway(tmp_path, 1, os.ttyname(second_slave))  # the mesh restarted: a new pty
        assert os.readlink(link) == os.ttyname(second_slave)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["gateway-1"]  # no leftover temporary link
        with open(link, "wb", buffering=0) as fh:  # what the daemon opens reaches the new pty
            fh.write(b"x")
        assert os.read(second_master, 1) == b"x"
    finally:
        for fd in (first_master, first_slave, second_master, second_slave):
            os.close(fd)
