"""The medium runs above the chips under a real-time policy (it stands for the wire)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml

from daemon_harness import stop_session
from support.emulator_procs import free_base_port

_SHOW = ("from cellbridge.emulator.realtime.realtime import above_the_chips; import os; "
         "print(above_the_chips(), os.sched_getparam(0).sched_priority)")


def _run(*prefix: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prefix, sys.executable, "-c", _SHOW], capture_output=True, text=True, timeout=30)


def test_under_a_real_time_policy_it_rises_one_priority() -> None:
    if shutil.which("chrt") is None:
        pytest.skip("no chrt here")
    probe = subprocess.run(["chrt", "-f", "3", "true"], capture_output=True, timeout=10)
    if probe.returncode != 0:
        pytest.skip("real-time priorities are not permitted here")
    out = _run("chrt", "-f", "3")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["4", "4"]


def test_at_the_top_priority_or_without_a_real_time_policy_it_stays() -> None:
    out = _run()
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["None", "0"]
    if shutil.which("chrt") is None or subprocess.run(["chrt", "-f", "99", "true"], capture_output=True,
                                                      timeout=10).returncode != 0:
        return
    top = _run("chrt", "-f", "99")
    assert top.stdout.split() == ["None", "99"], top.stderr


def test_mesh_up_under_chrt_starts_the_medium_above_the_bridges(tmp_path) -> None:
    """The real supervisor: its medium one priority above its bridges."""
    if shutil.which("chrt") is None or subprocess.run(["chrt", "-f", "1", "true"], capture_output=True,
                                                      timeout=10).returncode != 0:
        pytest.skip("real-time priorities are not permitted here")
    mesh = tmp_path / "line.toml"
    mesh.write_text(mesh_to_toml(meshgen.line(2)))
    port = free_base_port()
    up = subprocess.Popen(["chrt", "-f", "1", sys.executable, "-m", "cellbridge", "mesh", "up", str(mesh),
                           "--base-port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          start_new_session=True)
    try:
        prio: dict[str, int] = {}
        end = time.monotonic() + 30
        while time.monotonic() < end and not ({"medium", "bridge"} <= set(prio)):
            time.sleep(0.2)
            ps = subprocess.run(["ps", "-o", "rtprio=,args=", "-s", str(up.pid)], capture_output=True,
                                text=True, timeout=10).stdout
            for line in ps.splitlines():
                rt, _, cmd = line.strip().partition(" ")
                for name in ("medium", "bridge"):
                    if f"cellbridge {name} " in cmd and rt.isdigit():
                        prio[name] = int(rt)
        assert prio == {"medium": 2, "bridge": 1}, prio
    finally:
        stop_session(up)


def test_with_reset_on_fork_it_still_rises_one_priority() -> None:
    """``chrt -R``: sched_getscheduler reports the policy with SCHED_RESET_ON_FORK or-ed
    in, which the helper took for no real-time policy (a medium started so stayed at its
    bridges' priority); the flag is kept."""
    if shutil.which("chrt") is None or subprocess.run(["chrt", "-f", "-R", "3", "true"], capture_output=True,
                                                      timeout=10).returncode != 0:
        pytest.skip("real-time priorities (with reset-on-fork) are not permitted here")
    show = _SHOW.replace("print(", "print(os.sched_getscheduler(0) & os.SCHED_RESET_ON_FORK != 0, ")
    out = subprocess.run(["chrt", "-f", "-R", "3", sys.executable, "-c", show], capture_output=True, text=True,
                         timeout=30)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "4", "4"]
