"""What a hostile review of the emulator's process shells found (issue 17, points
15, 17-19): real processes, real ptys and sockets on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

import pytest

from cellbridge.emulator import meshgen
from cellbridge.emulator.mesh import mesh_to_toml
from test_emulator_processes import PY, free_base_port, running_skin, stop_and_sweep, terminate


def _grid(tmp_path: Path, name: str = "skin.toml") -> Path:
    path = tmp_path / name
    path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    return path


def test_a_second_mesh_up_on_a_base_port_in_use_exits_naming_the_port_and_starts_no_bridge(tmp_path):
    """The second mesh's medium and world failed to bind, it took 'address in use' for
    'my medium is up' and forked its bridges onto the first mesh's medium: one origin
    then carried two bridges' samples."""
    with running_skin(tmp_path) as skin:
        second = _grid(tmp_path, "second.toml")
        proc = subprocess.Popen([*PY, "mesh", "up", str(second), "--base-port", str(skin.base)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            stop_and_sweep(proc, second)
            pytest.fail("the second mesh up kept running on a base port in use")
        finally:
            stop_and_sweep(proc, second)
        assert proc.returncode != 0
        assert str(skin.base) in err.decode(), err
        assert b"gateway" not in out  # no line of a skin that does not run
        assert not [p for p in _processes(str(second)) if b"bridge" in _cmdline(p)]


def test_a_second_process_for_a_running_bridge_id_is_refused(tmp_path):
    with running_skin(tmp_path) as skin:
        # Bridge 4 runs under mesh up; a second one with the same id and ports must not.
        deadline = time.monotonic() + 30
        while not [p for p in _processes(str(skin.mesh_path)) if b"--id 4" in _cmdline(p)]:
            assert time.monotonic() < deadline, "bridge 4 never started"
            time.sleep(0.1)
        proc = subprocess.Popen([*PY, "bridge", "--mesh", str(skin.mesh_path), "--id", "4",
                                 "--base-port", str(skin.base)],
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            terminate(proc)
            pytest.fail("a second bridge 4 ran beside the first")
        assert proc.returncode != 0
        assert b"bridge 4" in err and b"already" in err, err


def _processes(text: str) -> list[int]:
    from test_emulator_processes import processes_mentioning

    return processes_mentioning(text)


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
    except OSError:
        return b""
