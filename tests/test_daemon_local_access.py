"""Local users: control over ipc:// restricted to a group by the socket file's mode and group.

Over loopback TCP every local user may tare or reconfigure the bridges. An ipc://
endpoint is a file: the daemon sets its mode and group right after binding
(``ipc_mode``, ``ipc_group``), whatever umask it was started with, so only the group's
members can connect.
"""

from __future__ import annotations

import grp
import os
import stat
import subprocess
from pathlib import Path

from daemon_harness import CLI, Client, Pty, daemon, write_config


def _no_umask() -> None:
    os.umask(0)  # what the unit's UMask=0000 used to give: world-writable sockets


def test_ipc_control_gets_the_configured_mode_and_group(tmp_path: Path) -> None:
    group = grp.getgrgid(os.getgid()).gr_name
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    control = tmp_path / "control"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False},
                             pub={"endpoint": f"ipc://{tmp_path}/pub"},
                             control={"endpoint": f"ipc://{control}", "ipc_mode": 0o660, "ipc_group": group})
    client = Client(endpoints, (b"health",))
    try:
        with daemon(cfg, tmp_path / "stderr.log", preexec_fn=_no_umask):
            client.ready()
            st = control.stat()
            assert stat.S_ISSOCK(st.st_mode)
            assert stat.S_IMODE(st.st_mode) == 0o660 and st.st_gid == os.getgid()
            assert stat.S_IMODE((tmp_path / "pub").stat().st_mode) == 0o666  # the default for pub: anyone local
    finally:
        client.close()
        pty.close()


def test_check_refuses_an_unknown_group_and_a_mode_beyond_the_permission_bits(tmp_path: Path) -> None:
    cfg = tmp_path / "daemon.toml"
    write_config(cfg, [{"name": "gw", "url": "/dev/ttyUSB0"}],
                 control={"endpoint": f"ipc://{tmp_path}/control", "ipc_group": "no-such-group-here",
                          "ipc_mode": 0o4777})
    out = subprocess.run([CLI, "daemon", "--config", str(cfg), "--check"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2
    assert "control.ipc_group = 'no-such-group-here'" in out.stderr and "control.ipc_mode" in out.stderr
