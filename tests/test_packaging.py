"""The package as a user installs it: a real wheel and a real, separate virtual environment."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("protocol", "tactile", "emulator", "daemon")

pytestmark = pytest.mark.slow
#: What a build must not copy along: version control, virtual environments, caches and
#: earlier builds (of the checkout or of a test).
_NOT_SOURCE = shutil.ignore_patterns(".git", ".venv", "venv", "build", "dist", "*.egg-info", "__pycache__", ".*_cache",
                                     ".hypothesis")


def _sources(tmp_path: Path) -> Path:
    """A private copy of the project to build from. pip builds a source tree in place
    (setuptools' ``build/`` and ``*.egg-info`` inside it): the two tests here, each on its
    own pytest-xdist worker under ``make test``, built the checkout at once and one failed
    ("[Errno 17] File exists: 'build/bdist.linux-x86_64/wheel/cellbridge-0.1.0.dist-info'",
    2 runs in 3), and every run wrote into the user's checkout."""
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=_NOT_SOURCE)
    return src


def _build_state() -> list[tuple[str, int]]:
    """The checkout's build leftovers as they are: each path under ``build/`` and
    ``cellbridge.egg-info/`` (the directories too) with its modification time."""
    out = []
    for top in (ROOT / "build", ROOT / "cellbridge.egg-info"):
        if top.exists():
            out += [(str(p), p.stat().st_mtime_ns) for p in [top, *top.rglob("*")]]
    return sorted(out)


def test_wheel_puts_everything_under_cellbridge(tmp_path: Path) -> None:
    before = _build_state()
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                    "--wheel-dir", str(tmp_path), str(_sources(tmp_path))], check=True, cwd=tmp_path)
    assert _build_state() == before  # built elsewhere: a build beside it (the other worker's) cannot collide
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
    """pip installs the source tree, its build isolated and its dependencies resolved, into
    a new environment. The environment gets no pip of its own (ensurepip's copy: 5 of the
    test's 30 s of CPU); this one installs into it (``--python``), as its own would."""
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=False)
    py = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--quiet", str(_sources(tmp_path))],
                   check=True, env=env, cwd=tmp_path)
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
