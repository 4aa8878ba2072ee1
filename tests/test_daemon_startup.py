"""Start-up: a SIGHUP that arrives before the daemon's handler is installed must not kill it.

``systemctl reload`` (or a logrotate script) may send SIGHUP at any moment; until the
event loop installs its handler the default action of SIGHUP is to terminate. The
daemon defers SIGHUP from the first line of the command and takes it once its handler
is in place (as a reload).
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest

from daemon_harness import Client, Pty, daemon, write_config

SIGHUP_BIT = 1 << (signal.SIGHUP - 1)


def _mask(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1], 16)
    raise AssertionError(field)


def _loaded_libzmq(pid: int) -> bool:
    """libzmq is mapped once the command imports the daemon's modules: well inside start-up,
    long before the event loop runs."""
    try:
        return "libzmq" in Path(f"/proc/{pid}/maps").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_sighup_during_start_up_is_taken_as_a_reload(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False})
    client = Client(endpoints, (b"health",))
    log = tmp_path / "stderr.log"
    try:
        with daemon(cfg, log) as proc:
            end = time.monotonic() + 30.0
            while not _loaded_libzmq(proc.pid):
                assert proc.poll() is None and time.monotonic() < end, "the daemon never got to its imports"
                time.sleep(0.0005)
            caught_already = _mask(proc.pid, "SigCgt") & SIGHUP_BIT
            assert not caught_already, "too late to test: the handler was installed already"
            proc.send_signal(signal.SIGHUP)
            client.ready()
            assert proc.poll() is None, f"killed by a SIGHUP during start-up (exit {proc.returncode})"
            msgs = [json.loads(line)["msg"] for line in log.read_text().splitlines() if line.startswith("{")]
            assert "config reloaded" in msgs
            assert not _mask(proc.pid, "SigBlk") & SIGHUP_BIT, "SIGHUP is still blocked after start-up"
    finally:
        client.close()
        pty.close()


@pytest.mark.parametrize("taken", ["pub", "control"])
def test_a_second_daemon_on_taken_endpoints_says_so_in_a_sentence_and_exits(tmp_path: Path, taken: str) -> None:
    # two `cellbridge daemon` with the same config: the second said so only in a JSON log line
    import subprocess

    from daemon_harness import CLI, free_port

    pty = Pty(tmp_path / "gw")
    first_cfg, second_cfg = tmp_path / "first.toml", tmp_path / "second.toml"
    ends = write_config(first_cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False})
    other = "control" if taken == "pub" else "pub"
    write_config(second_cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False},
                 **{taken: {"endpoint": ends[taken]}, other: {"endpoint": f"tcp://127.0.0.1:{free_port()}"}})
    client = Client(ends, (b"health",))
    try:
        with daemon(first_cfg):
            client.ready()
            second = subprocess.run([CLI, "daemon", "--config", str(second_cfg)], capture_output=True, text=True,
                                    timeout=60, start_new_session=True)
    finally:
        client.close()
        pty.close()
    assert second.returncode != 0, second.stderr
    lines = second.stderr.splitlines()
    assert any(line.startswith("{") and "Address already in use" in line for line in lines), lines  # the log line
    said = [line for line in lines if line.startswith("cellbridge daemon:")]
    assert len(said) == 1, lines
    assert ends[taken] in said[0] and f"[{taken}] endpoint" in said[0] and "another daemon" in said[0], said
