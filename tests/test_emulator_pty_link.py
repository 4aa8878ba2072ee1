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


def test_mesh_up_makes_the_link_folder_and_refuses_one_it_cannot_make_before_starting(tmp_path: Path) -> None:
    # `mesh up --pty-link DIR` with DIR missing ended in a FileNotFoundError traceback, after
    # the medium and the world had started
    import subprocess

    from cellbridge.emulator.mesh import meshgen
    from cellbridge.emulator.mesh.mesh import mesh_to_toml

    from cellbridge.demo import gateway_line
    from support.emulator_procs import PY, free_base_port, processes_mentioning, stop_and_sweep

    mesh_path = tmp_path / "line-2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    (tmp_path / "afile").write_text("x")
    r = subprocess.run([*PY, "mesh", "up", str(mesh_path), "--pty-link", str(tmp_path / "afile" / "links"),
                        "--base-port", str(free_base_port())], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--pty-link" in r.stderr and "Nothing started" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and "medium:" not in r.stderr, r.stderr  # refused before the medium ran
    links = tmp_path / "links" / "skin"  # missing, two levels deep: made
    proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--pty-link", str(links), "--base-port",
                             str(free_base_port())], stdout=subprocess.PIPE, start_new_session=True)
    try:
        line = gateway_line(proc)
        assert line[-1] == str(links / "gateway-1") and os.readlink(links / "gateway-1") == line[2], line
    finally:
        stop_and_sweep(proc, mesh_path)
    assert processes_mentioning(str(mesh_path)) == []
