"""The package as a user installs it: a real wheel and a real, separate virtual environment."""

from __future__ import annotations

import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("protocol", "tactile", "emulator", "daemon")

pytestmark = pytest.mark.slow


def test_wheel_puts_everything_under_cellbridge(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                    "--wheel-dir", str(tmp_path), str(ROOT)], check=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("cellbridge-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"cellbridge"}
    for layer in LAYERS:
        assert f"cellbridge/{layer}/__init__.py" in names
        assert not any(n.startswith(f"{layer}/") for n in names)
    assert "cellbridge/protocol/frame.py" in names
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    assert "cellbridge = cellbridge.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()


def test_pip_install_into_a_new_venv(tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(ROOT)], check=True, env=env, cwd=tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    probe = (
        "import importlib.util, cellbridge.protocol as p, cellbridge;"
        "print(p.__file__);"
        "print([m for m in ('protocol', 'daemon', 'emulator', 'tactile') if importlib.util.find_spec(m)])"
    )
    out = subprocess.run([str(py), "-c", probe], check=True, env=env, cwd=elsewhere,
                         capture_output=True, text=True).stdout.splitlines()
    assert Path(out[0]).is_relative_to(env_dir), out[0]  # installed copy, not the source tree
    assert out[1] == "[]"  # no generic top-level modules
    version = subprocess.run([str(env_dir / "bin" / "cellbridge"), "--version"], check=True, env=env,
                             cwd=elsewhere, capture_output=True, text=True).stdout
    assert version.startswith("cellbridge ")
