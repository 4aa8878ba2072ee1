"""The units in systemd/: `systemd-analyze verify` passes, the daemon's exposure is 2.0 or less.

verify insists that ExecStart's binary exists, so the units are checked as copies
whose /usr/local/bin/cellbridge is the cellbridge installed with this suite.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from daemon_harness import CLI

UNITS_DIR = Path(__file__).resolve().parent.parent / "systemd"
UNITS = sorted(p.name for p in UNITS_DIR.glob("*.service"))
INSTALLED_PATH = "/usr/local/bin/cellbridge"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed on this machine")


def directives(unit: str) -> list[tuple[str, str, str]]:
    """(section, key, value) of every assignment, in order (keys repeat in unit files)."""
    section, out = "", []
    for line in (UNITS_DIR / unit).read_text().splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        elif line and not line.startswith(("#", ";")):
            key, _, value = line.partition("=")
            out.append((section, key, value))
    return out


def values(unit: str, key: str) -> list[str]:
    return [v for s, k, v in directives(unit) if s == "Service" and k == key]


def installed_copies(tmp_path: Path) -> list[Path]:
    cli = Path(shutil.which(CLI) or CLI).resolve()
    assert cli.is_file(), f"the installed cellbridge command is needed: {cli}"
    copies = []
    for unit in UNITS:
        text = (UNITS_DIR / unit).read_text()
        assert INSTALLED_PATH in text, f"{unit}: ExecStart should run {INSTALLED_PATH}"
        (tmp_path / unit).write_text(text.replace(INSTALLED_PATH, str(cli)))
        copies.append(tmp_path / unit)
    return copies


def test_units_exist() -> None:
    assert "cellbridge-daemon.service" in UNITS and "cellbridge-mesh.service" in UNITS


def test_daemon_unit_is_notify_watchdog_non_root_with_serial_access() -> None:
    unit = "cellbridge-daemon.service"
    assert values(unit, "Type") == ["notify"]
    assert values(unit, "WatchdogSec") and values(unit, "NotifyAccess") == ["main"]
    assert values(unit, "ExecStart") == [f"{INSTALLED_PATH} daemon --config /etc/cellbridge/daemon.toml"]
    assert values(unit, "ExecReload") == ["kill -HUP $MAINPID"]
    assert values(unit, "DynamicUser") == ["yes"] or values(unit, "User") not in ([], ["root"])
    assert values(unit, "SupplementaryGroups") == ["dialout"]
    allowed = values(unit, "DeviceAllow")
    assert "char-ttyUSB rw" in allowed and "char-ttyACM rw" in allowed
    assert values(unit, "DevicePolicy") == ["closed"]


def test_mesh_unit_runs_mesh_up() -> None:
    (exec_start,) = values("cellbridge-mesh.service", "ExecStart")
    assert exec_start.startswith(f"{INSTALLED_PATH} mesh up ") and exec_start.endswith(".toml")


@needs_analyze
def test_systemd_analyze_verify_passes(tmp_path: Path) -> None:
    copies = installed_copies(tmp_path)
    assert ANALYZE is not None
    out = subprocess.run([ANALYZE, "verify", *map(str, copies)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    complaints = [ln for ln in out.stderr.splitlines() if "cellbridge" in ln]
    assert not complaints, complaints


@needs_analyze
@pytest.mark.parametrize(("unit", "limit"), [("cellbridge-daemon.service", 2.0), ("cellbridge-mesh.service", 2.0)])
def test_exposure_is_at_most(unit: str, limit: float, tmp_path: Path) -> None:
    copy = next(p for p in installed_copies(tmp_path) if p.name == unit)
    assert ANALYZE is not None
    out = subprocess.run([ANALYZE, "security", "--offline=yes", str(copy)], capture_output=True, text=True,
                         timeout=120)
    match = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", out.stdout)
    assert match, out.stdout + out.stderr
    assert float(match.group(1)) <= limit, out.stdout


ESTIMATE_UNDER_UNIT = r"""
import ctypes, sys
if sys.argv[1] == "yes":
    # PR_SET_MDWE / PR_MDWE_REFUSE_EXEC_GAIN: what systemd applies for MemoryDenyWriteExecute=yes.
    if ctypes.CDLL(None, use_errno=True).prctl(65, 1, 0, 0, 0) != 0:
        print("no mdwe")
        sys.exit(0)
from cellbridge.tactile import ContactEstimator, grid_layout, skin_response
lay = grid_layout(2, 2)
(c,) = ContactEstimator(lay).estimate(*skin_response(lay, [[0.02, 0.0, 3.0, 0.012]]))
print("estimated", round(c.x, 6))
"""


def test_daemon_unit_lets_the_contact_kernels_compile_and_keeps_their_cache() -> None:
    """The daemon runs the contact estimator, whose kernels numba compiles to machine
    code: the unit must allow executable memory, and give numba a writable cache
    (the installation is read-only, the home hidden) or every start pays ≈ 20 s of
    compiling, longer than the watchdog's period."""
    unit = "cellbridge-daemon.service"
    env = dict(v.split("=", 1) for e in values(unit, "Environment") for v in e.split())
    (cache,) = values(unit, "CacheDirectory")
    assert env.get("NUMBA_CACHE_DIR", "").startswith(f"/var/cache/{cache}/"), env
    mdwe = (values(unit, "MemoryDenyWriteExecute") or ["no"])[-1]
    # The kernels' own cache (next to the modules) keeps this run short.
    r = subprocess.run([sys.executable, "-c", ESTIMATE_UNDER_UNIT, mdwe], capture_output=True, text=True,
                       timeout=300)
    if r.stdout.strip() == "no mdwe":
        pytest.skip("this kernel has no PR_SET_MDWE (Linux < 6.3)")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "estimated 0.02"


def test_daemon_unit_keeps_its_files_private_and_has_descriptors_for_its_peer_bounds() -> None:
    """UMask=0000 made ipc sockets and captures world-writable; the descriptor limit must
    hold every peer the daemon admits (docs/daemon.md, Limits) plus a reserve for its lines."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.ops.peers import descriptors_needed

    unit = "cellbridge-daemon.service"
    (umask,) = values(unit, "UMask")
    assert int(umask, 8) & 0o007 == 0o007, "others must get nothing"
    (nofile,) = values(unit, "LimitNOFILE")
    assert int(nofile) >= descriptors_needed(parse_config({"link": [{"url": "/dev/ttyUSB0"}] * 8}))
